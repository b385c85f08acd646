//! report.md laid out like the paper's tables, and the files of a sweep's output.

use super::*;

use crate::error::{SimError, StepContext};
use markhold_exposure::{ExposureMethod, METHODS};
use markhold_hil::scene::LightingScenario;

/// The paper's numbers for the report, from each method's row of
/// [`markhold_exposure::METHODS`].
pub(super) mod paper {
    use markhold_exposure::ExposureMethod;
    use markhold_hil::scene::LightingScenario;

    /// Static marker in a river, 1 minute: det(cov) m^6, detection %, max distance m.
    pub fn static_precision(m: ExposureMethod) -> Option<(f64, f64, f64)> {
        m.info().paper.static_precision
    }

    /// Moving camera, adversarial light only: mean distance m, detection %.
    pub fn motion(m: ExposureMethod, l: LightingScenario) -> Option<String> {
        if l != LightingScenario::Adversarial {
            return None;
        }
        m.info().paper.motion_adversarial.map(str::to_string)
    }

    /// Convergence seconds (the paper's AAEC is momentum + RoI; no GEC or Default row).
    pub fn convergence_s(m: ExposureMethod, l: LightingScenario) -> Option<f64> {
        let row = m.info().paper.convergence_s?;
        match l {
            LightingScenario::Adversarial => Some(row[0]),
            LightingScenario::Normal => Some(row[1]),
            LightingScenario::Low => Some(row[2]),
            LightingScenario::Caustics => None,
        }
    }
}

/// How a metric is printed.
#[derive(Clone, Copy)]
pub(super) enum Fmt {
    Percent,
    Sci,
    Metres,
    Seconds,
    Micros,
    Ratio,
    /// A 0/1 flag: the fraction of seeds where it was set.
    Flag,
}

pub(super) fn fmt_value(v: f64, f: Fmt) -> String {
    match f {
        Fmt::Percent => format!("{:.1} %", 100.0 * v),
        Fmt::Sci => format!("{v:.2e}"),
        Fmt::Metres => format!("{v:.4}"),
        Fmt::Seconds => format!("{v:.2}"),
        Fmt::Micros => format!("{v:.0}"),
        Fmt::Ratio => format!("{v:.2}"),
        Fmt::Flag => {
            if v == 0.0 {
                "no".to_string()
            } else if v == 1.0 {
                "yes".to_string()
            } else {
                format!("{:.0} % of seeds", 100.0 * v)
            }
        }
    }
}

/// `mean ± h` over seeds, h the half-width of the 95 % interval (symmetric: Student t);
/// `-` where the metric is undefined (e.g. no detection).
pub(super) fn fmt_stat(s: Option<&Stat>, f: Fmt) -> String {
    let Some(s) = s else { return "-".to_string() };
    match (s.mean, s.ci95_half(), f) {
        (None, _, _) => "-".to_string(),
        (Some(m), _, Fmt::Flag) => fmt_value(m, f),
        (Some(m), Some(h), _) => format!("{} ± {}", fmt_value(m, f), fmt_value(h, f)),
        (Some(m), None, _) => fmt_value(m, f),
    }
}

/// The paper's cell for a method, if it has one.
pub(super) type PaperColumn<'a> = &'a dyn Fn(ExposureMethod) -> Option<String>;

/// One table: a row per method, the given metric columns, and an optional paper column.
pub(super) fn table(
    out: &mut String,
    r: &CompareResults,
    l: LightingScenario,
    cols: &[(&str, &str, Fmt)],
    paper: Option<(&str, PaperColumn)>,
) {
    use std::fmt::Write as _;
    let mut head = String::from("| Method |");
    let mut rule = String::from("|---|");
    for (title, _, _) in cols {
        let _ = write!(head, " {title} |");
        rule.push_str("---|");
    }
    if let Some((title, _)) = &paper {
        let _ = write!(head, " {title} |");
        rule.push_str("---|");
    }
    let _ = writeln!(out, "{head}\n{rule}");
    for &m in &r.methods {
        let stats = r.case_stats(m, l);
        let _ = write!(out, "| {} |", m.label());
        for (_, key, f) in cols {
            let _ = write!(
                out,
                " {} |",
                fmt_stat(stats.and_then(|s| s.metrics.get(*key)), *f)
            );
        }
        if let Some((_, p)) = &paper {
            let _ = write!(out, " {} |", p(m).unwrap_or_else(|| "-".to_string()));
        }
        out.push('\n');
    }
    out.push('\n');
}

/// `report.md`: the four experiments laid out like the paper's tables, one block per
/// lighting, mean ± sample sd over seeds, the paper's numbers beside ours where it has them.
pub fn report_markdown(r: &CompareResults, plots: &[String]) -> String {
    let mut o = String::new();
    report_header(&mut o, r);
    report_static_precision(&mut o, r);
    report_motion_tracking(&mut o, r);
    report_convergence(&mut o, r);
    report_convergence_to_optimum(&mut o, r);
    report_station_keeping(&mut o, r);
    report_claims(&mut o, r);
    report_lockstep_timeouts(&mut o, r);
    report_plots(&mut o, plots);
    o
}

/// The title and what the cells mean.
pub(super) fn report_header(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let seeds = r.seeds.len();
    // markhold's variants of published methods, and what each is.
    let variants: Vec<(&str, &str)> = METHODS
        .iter()
        .filter_map(|i| Some((i.label, i.variant_of?)))
        .collect();
    let _ = writeln!(o, "# markhold compare: {}\n", inline_text(&r.site));
    let _ = writeln!(
        o,
        "Site file `{}`, {}x{} px at {} fps, {} simulated seconds per run, seeds {:?}. \
         Cells are the mean over {} seed(s) ± the half-width of its 95 % confidence \
         interval (Student t with n - 1 degrees of freedom; none with one seed); `-` where \
         the metric is undefined (no detection). {} are the methods as the paper's code ran \
         them; {} are {}. The paper's numbers are from its own camera and water; ours are \
         from the HIL world.\n",
        inline_text(&r.site_file),
        r.width_px,
        r.height_px,
        r.fps,
        r.seconds,
        r.seeds,
        seeds,
        prose_list(METHODS.iter().filter(|i| i.paper_code).map(|i| i.label)),
        prose_list(variants.iter().map(|(label, _)| *label)),
        prose_list(variants.iter().map(|(_, what)| *what)),
    );
}

/// `a`, `a and b`, `a, b and c`.
pub(super) fn prose_list<'a>(items: impl Iterator<Item = &'a str>) -> String {
    let items: Vec<&str> = items.collect();
    match items.split_last() {
        None => String::new(),
        Some((last, [])) => (*last).to_string(),
        Some((last, rest)) => format!("{} and {last}", rest.join(", ")),
    }
}

/// Text from a results file (a site's name, a path) for one line of Markdown: control
/// characters (newlines, escapes) shown escaped, backticks as quotes, at most 200
/// characters, so it cannot start a heading or leave its code span.
pub fn inline_text(s: &str) -> String {
    let mut out = String::with_capacity(s.len().min(200));
    for (n, c) in s.chars().enumerate() {
        if n == 200 {
            out.push_str("...");
            break;
        }
        match c {
            '`' => out.push('\''),
            c if c.is_control() => out.extend(c.escape_default()),
            c => out.push(c),
        }
    }
    out
}

/// Frames to reach the scene's optimum: the mean over the seeds that reach it ± its
/// interval, "never" when none does, and how many do when not all.
pub(super) fn fmt_reach(stats: Option<&CaseStats>, frames_key: &str, seeds: usize) -> String {
    let Some(st) = stats.and_then(|s| s.metrics.get(frames_key)) else {
        return "-".to_string();
    };
    if st.n == 0 {
        return "never".to_string();
    }
    let cell = fmt_stat(Some(st), Fmt::Micros);
    if st.n < seeds {
        format!("{cell} ({} of {seeds} seeds)", st.n)
    } else {
        cell
    }
}

/// Section 3b: convergence against the scene's own optimum, a table per lighting.
pub(super) fn report_convergence_to_optimum(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "### Convergence to the scene's optimum\n\nThe same runs against the optimum of \
         their scene, found by sweeping the exposure over the camera's range in 3 % steps \
         on the still station view (two frames each, whatever the method): the argmax of \
         the paper's M (its published form, G = Ix^2 + Iy^2 ranked by G, on the marker's \
         box + 10 %), the exposures where M is within 5 % of its best, and those whose \
         detection rate is within 5 points of the best. Frames until the exposure stays \
         within 5 % of the argmax / in the M band / in the detection band, mean over the \
         seeds that get there (never: no seed was there at the end of the run).\n"
    );
    let seeds = r.seeds.len();
    for &l in &r.lightings {
        let _ = writeln!(
            o,
            "#### Convergence to the optimum, {l} lighting\n\n| Method | argmax of M [us] | \
             From 10x long: to argmax | to M band | to detection band | final / argmax | \
             From 10x short: to argmax | to M band | to detection band | final / argmax |\n\
             |---|---|---|---|---|---|---|---|---|---|"
        );
        for &m in &r.methods {
            let st = r.case_stats(m, l);
            let get = |k: &str| fmt_stat(st.and_then(|s| s.metrics.get(k)), Fmt::Ratio);
            let _ = write!(
                o,
                "| {} | {} |",
                m.label(),
                fmt_stat(
                    st.and_then(|s| s.metrics.get("convergence.optimum.m_argmax_us")),
                    Fmt::Micros
                )
            );
            let never_seen = st
                .and_then(|s| s.metrics.get("convergence.optimum.detection_best"))
                .and_then(|s| s.mean)
                .is_some_and(|v| v == 0.0);
            for side in ["long", "short"] {
                for k in ["m_argmax", "m_band", "detection_band"] {
                    let key = format!("convergence.{side}.frames_to_{k}");
                    let cell = if k == "detection_band" && never_seen {
                        "no exposure detects".to_string()
                    } else {
                        fmt_reach(st, &key, seeds)
                    };
                    let _ = write!(o, " {cell} |");
                }
                let _ = write!(
                    o,
                    " {} |",
                    get(&format!("convergence.{side}.final_over_m_argmax"))
                );
            }
            o.push('\n');
        }
        o.push('\n');
    }
}

/// Section 1: static precision, a table per lighting.
pub(super) fn report_static_precision(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "## 1. Static precision\n\nVehicle held fixed on station for {} s. det(cov): \
         determinant of the 3x3 covariance of the measured marker positions (camera frame, \
         m^6). Paper: a static marker in a river, 1 minute.\n",
        r.seconds
    );
    for &l in &r.lightings {
        let _ = writeln!(o, "### Static precision, {l} lighting\n");
        let p = |m| {
            paper::static_precision(m)
                .map(|(d, rate, max)| format!("{d:.2e} / {rate} % / {max:.4} m"))
        };
        table(
            o,
            r,
            l,
            &[
                ("det(cov) [m^6]", "static.position_cov_det_m6", Fmt::Sci),
                ("Detection", "static.detection_rate", Fmt::Percent),
                ("Max distance [m]", "static.max_distance_m", Fmt::Metres),
                ("Mean bias [m]", "static.mean_bias_m", Fmt::Metres),
                (
                    "Final exposure [us]",
                    "static.final_exposure_us",
                    Fmt::Micros,
                ),
            ],
            Some(("Paper det / detection / max", &p)),
        );
    }
}

/// Section 2: motion tracking, the traverse, then a table per lighting.
pub(super) fn report_motion_tracking(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "## 2. Motion tracking\n\nCamera moved sideways at constant speed so the marker \
         crosses the middle of the view. Distance to trajectory: mean distance from each \
         measured position to the polyline of true positions (the paper's metric); error: \
         to the true position of the same frame.\n"
    );
    if let Some(c) = r.cases.first() {
        let _ = writeln!(
            o,
            "Traverse {:.3} m at {:.4} m/s.\n",
            c.motion_tracking.span_m, c.motion_tracking.speed_mps
        );
    }
    for &l in &r.lightings {
        let _ = writeln!(o, "### Motion tracking, {l} lighting\n");
        let p = move |m| paper::motion(m, l);
        table(
            o,
            r,
            l,
            &[
                (
                    "Distance to trajectory [m]",
                    "motion.mean_distance_to_trajectory_m",
                    Fmt::Metres,
                ),
                ("Detection", "motion.detection_rate", Fmt::Percent),
                ("Same-frame error [m]", "motion.mean_error_m", Fmt::Metres),
            ],
            Some(("Paper distance / detection", &p)),
        );
    }
}

/// Section 3: convergence from 10x long and 10x short, a table per lighting.
pub(super) fn report_convergence(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "## 3. Convergence\n\nVehicle fixed on station; exposure started at 10x and 1/10 of \
         the exposure the method settled on in the static run (clamped to the camera's \
         limits). Seconds until the exposure is first within 5% of the run's final value, and \
         until it stays there (an excursion after the first entry counts only in the \
         second); \
         settled: it stayed there for at least the last second; oscillates: it crossed the \
         band from one side to the other at least twice; final / reference: where it ended over \
         where the static run settled (1.00: back where it belongs; a method can also \
         settle, within 5%, at a camera limit). Paper: its AAEC with momentum and RoI, \
         AEC; it has no GEC or Default convergence numbers.\n"
    );
    for &l in &r.lightings {
        let _ = writeln!(o, "### Convergence, {l} lighting\n");
        let p = move |m| paper::convergence_s(m, l).map(|s| format!("{s} s"));
        table(
            o,
            r,
            l,
            &[
                (
                    "From 10x long: first within [s]",
                    "convergence.long.first_within_seconds",
                    Fmt::Seconds,
                ),
                (
                    "From 10x long: stays within [s]",
                    "convergence.long.seconds",
                    Fmt::Seconds,
                ),
                ("Settled", "convergence.long.settled", Fmt::Flag),
                ("Oscillates", "convergence.long.oscillates", Fmt::Flag),
                (
                    "Final / reference",
                    "convergence.long.final_over_reference",
                    Fmt::Ratio,
                ),
                (
                    "From 10x short: first within [s]",
                    "convergence.short.first_within_seconds",
                    Fmt::Seconds,
                ),
                (
                    "From 10x short: stays within [s]",
                    "convergence.short.seconds",
                    Fmt::Seconds,
                ),
                ("Settled", "convergence.short.settled", Fmt::Flag),
                ("Oscillates", "convergence.short.oscillates", Fmt::Flag),
                (
                    "Final / reference",
                    "convergence.short.final_over_reference",
                    Fmt::Ratio,
                ),
            ],
            Some(("Paper [s]", &p)),
        );
    }
}

/// Section 4: station keeping with the full loop, a table per lighting.
pub(super) fn report_station_keeping(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "## 4. Station keeping\n\nThe full loop from the site's initial offset for {} s. \
         det(cov): determinant of the covariance of the true vehicle position (marker \
         frame) over the last half; position RMS: vehicle to station, last half. Paper: \
         AAEC had the smallest determinant in all three lightings (no numbers quoted here).\n",
        r.seconds
    );
    for &l in &r.lightings {
        let _ = writeln!(o, "### Station keeping, {l} lighting\n");
        table(
            o,
            r,
            l,
            &[
                ("det(cov) [m^6]", "station.position_cov_det_m6", Fmt::Sci),
                ("Detection", "station.detection_rate", Fmt::Percent),
                ("Position RMS [m]", "station.position_rms_m", Fmt::Metres),
                (
                    "Measured det(cov) [m^6]",
                    "station.measured_position_cov_det_m6",
                    Fmt::Sci,
                ),
            ],
            None,
        );
    }
}

/// Section 5: the paper's claims, paired over seeds.
pub(super) fn report_claims(o: &mut String, r: &CompareResults) {
    use crate::claims::{Scale, Verdict};
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "## 5. The paper's claims, paired over seeds\n\nEach AAEC against each other method \
         on the same seeds: the mean of the per-seed difference (AAEC - other; log10 for \
         determinants) with its 95 % confidence interval, and the two-sided paired-t p-value \
         of no difference. n: seeds where both have the metric; AAEC only / other only: \
         seeds where one of them has it (e.g. only it detects the marker). Holds: AAEC \
         better on average with p < 0.05, or it has the metric on every seed and the other \
         on none.\n"
    );
    if r.claims.is_empty() {
        let _ = writeln!(
            o,
            "No claim applies: the sweep needs an AAEC and another method in a paper \
             lighting.\n"
        );
        return;
    }
    let _ = writeln!(
        o,
        "| Claim | Lighting | AAEC | Other | n | AAEC only / other only | Mean difference [95 % CI] | p | Verdict |\n|---|---|---|---|---|---|---|---|---|"
    );
    for c in &r.claims {
        let unit = match c.scale {
            Scale::Log10 => " (log10)",
            Scale::Linear => "",
        };
        let diff = match (c.mean_diff, c.ci95_low, c.ci95_high) {
            (Some(d), Some(lo), Some(hi)) => format!("{d:.4} [{lo:.4}, {hi:.4}]{unit}"),
            (Some(d), _, _) => format!("{d:.4}{unit}"),
            _ => "-".to_string(),
        };
        let p = c.p.map_or("-".to_string(), |p| {
            if p < 1e-4 {
                format!("{p:.1e}")
            } else {
                format!("{p:.4}")
            }
        });
        let verdict = match c.verdict {
            Verdict::Holds => "holds",
            Verdict::NotSignificant => "not significant",
            Verdict::Against => "against",
            Verdict::Untested => "untested",
        };
        let _ = writeln!(
            o,
            "| {} | {} | {} | {} | {} | {} / {} | {diff} | {p} | {verdict} |",
            c.claim,
            c.lighting,
            c.method.label(),
            c.other.label(),
            c.n,
            c.method_only,
            c.other_only,
        );
    }
    o.push('\n');
}

/// The lock-step timeouts over all runs.
pub(super) fn report_lockstep_timeouts(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let timeouts: u64 = r.cases.iter().map(|c| c.lockstep_timeouts).sum();
    let _ = writeln!(
        o,
        "Lock-step timeouts over all runs: {timeouts} (frames the simulated vehicle stepped \
         without its command; 0 in a healthy run).\n"
    );
}

/// Links to the plots, if any were written.
pub(super) fn report_plots(o: &mut String, plots: &[String]) {
    use std::fmt::Write as _;
    if !plots.is_empty() {
        let _ = writeln!(o, "## Plots\n");
        for p in plots {
            let _ = writeln!(o, "- [{p}]({p})");
        }
    }
}

/// Write `results.json`, the plots and `report.md` into `dir` (created if missing).
/// Returns the files written, relative to `dir`.
pub fn write_outputs(out: &CompareOutput, dir: &std::path::Path) -> Result<Vec<String>, SimError> {
    std::fs::create_dir_all(dir).step(|| format!("creating --out {}", dir.display()))?;
    let json = serde_json::to_string_pretty(&out.results)?;
    let p = dir.join("results.json");
    std::fs::write(&p, json + "\n").step(|| format!("writing {}", p.display()))?;
    let mut files = vec!["results.json".to_string()];
    let p = dir.join("timings.json");
    let t = serde_json::to_string_pretty(&out.timings)?;
    std::fs::write(&p, t + "\n").step(|| format!("writing {}", p.display()))?;
    files.push("timings.json".to_string());
    let plots = crate::plots::write_plots(out, dir)?;
    let md = report_markdown(&out.results, &plots);
    let p = dir.join("report.md");
    std::fs::write(&p, md).step(|| format!("writing {}", p.display()))?;
    files.push("report.md".to_string());
    files.extend(plots);
    Ok(files)
}
