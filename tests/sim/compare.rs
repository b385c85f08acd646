//! `markhold compare` end to end on a small site: every table, plot and JSON field, and
//! the paper's headline result (AAEC sees the marker in adversarial light, Default does not).
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::path::Path;

use crate::common::{markhold, tmp_path};

use markhold::sim::compare::{run_compare, CompareOptions, CompareResults};
use markhold_exposure::ExposureMethod;
use markhold_hil::scene::LightingScenario;

const SITE: &str = "tests/fixtures/pool-640.toml";

fn out_dir(name: &str) -> std::path::PathBuf {
    tmp_path("compare", name)
}

#[test]
fn compare_writes_every_table_plot_and_field() {
    let out = out_dir("compare-e2e");
    run_small_compare(&out);
    assert_plots(&out);
    assert_report(&out);
    let r = assert_results_json(&out);
    assert_paper_claim(&r);
}

/// Two methods, adversarial light, one seed, 3 s, into `out`.
fn run_small_compare(out: &Path) {
    let status = markhold()
        .args([
            "compare",
            "--site",
            SITE,
            "--seeds",
            "1",
            "--seconds",
            "3",
            "--methods",
            "aaec,default",
            "--lightings",
            "adversarial",
            "--jobs",
            "2",
            "--quiet",
            "--out",
        ])
        .arg(out)
        .env("RUST_LOG", "error")
        .status()
        .expect("running markhold compare");
    assert!(status.success(), "markhold compare failed: {status}");
}

/// Plots: four kinds per lighting, PNG and SVG, non-trivial files.
fn assert_plots(out: &Path) {
    for l in ["adversarial"] {
        for kind in ["static_scatter", "motion_tracks", "exposure", "spread"] {
            for ext in ["png", "svg"] {
                let p = out.join(format!("{kind}_{l}.{ext}"));
                let len = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
                assert!(
                    len > 2000,
                    "{} missing or nearly empty ({len} bytes)",
                    p.display()
                );
            }
        }
        let png = std::fs::read(out.join(format!("exposure_{l}.png"))).expect("png");
        assert_eq!(&png[1..4], b"PNG");
    }
}

/// Report: the four experiments' tables for each lighting, a row per method.
fn assert_report(out: &Path) {
    let report = std::fs::read_to_string(out.join("report.md")).expect("report.md");
    for l in ["adversarial"] {
        for title in [
            "Static precision",
            "Motion tracking",
            "Convergence",
            "Station keeping",
        ] {
            let h = format!("### {title}, {l} lighting");
            assert!(report.contains(&h), "report.md lacks '{h}'");
        }
    }
    for col in [
        "det(cov) [m^6]",
        "Max distance [m]",
        "Distance to trajectory [m]",
        "From 10x long: stays within [s]",
        "From 10x long: first within [s]",
        "From 10x short: stays within [s]",
        "Oscillates",
        "Position RMS [m]",
        "Paper det / detection / max",
    ] {
        assert!(report.contains(col), "report.md lacks column '{col}'");
    }
    // Convergence against the scene's optimum, beside the existing measure.
    for t in [
        "### Convergence to the scene's optimum",
        "#### Convergence to the optimum, adversarial lighting",
        "argmax of M [us]",
        "From 10x long: to argmax",
        "to detection band",
    ] {
        assert!(report.contains(t), "report.md lacks '{t}'");
    }
    // Two methods x four experiments, and the optimum's table.
    assert_eq!(report.matches("\n| AAEC (markhold) |").count(), 5);
    assert_eq!(report.matches("\n| Default |").count(), 5);
    assert!(
        !report.contains("normal lighting"),
        "only the asked lighting"
    );
}

/// JSON: every field present (typed parse) and every metric aggregated.
fn assert_results_json(out: &Path) -> CompareResults {
    let text = std::fs::read_to_string(out.join("results.json")).expect("results.json");
    let raw: serde_json::Value = serde_json::from_str(&text).expect("valid JSON");
    for key in [
        "site",
        "fps",
        "seconds",
        "seeds",
        "methods",
        "lightings",
        "cases",
        "stats",
        "claims",
    ] {
        assert!(raw.get(key).is_some(), "results.json lacks '{key}'");
    }
    let case = &raw["cases"][0];
    for (exp, fields) in [
        (
            "static_precision",
            &["detection_rate", "position_cov_det_m6", "max_distance_m"][..],
        ),
        (
            "motion_tracking",
            &[
                "detection_rate",
                "mean_distance_to_trajectory_m",
                "mean_error_m",
            ][..],
        ),
        (
            "convergence",
            &["reference_exposure_us", "from_long", "from_short"][..],
        ),
        (
            "station_keeping",
            &["detection_rate", "position_cov_det_m6", "position_rms_m"][..],
        ),
    ] {
        for f in fields {
            assert!(
                case[exp].get(*f).is_some(),
                "results.json case lacks {exp}.{f}"
            );
        }
    }
    let convergence: [(&str, &[&str]); 2] = [
        (
            "from_long",
            &[
                "frames",
                "seconds",
                "settled",
                "oscillates",
                "frames_to_m_argmax",
                "frames_to_m_band",
                "frames_to_detection_band",
                "final_over_m_argmax",
            ],
        ),
        (
            "optimum",
            &[
                "m_argmax_us",
                "m_band_us",
                "detection_best",
                "detection_band_us",
            ],
        ),
    ];
    for (part, fields) in convergence {
        for f in fields {
            assert!(case["convergence"][part].get(f).is_some(), "{part}.{f}");
        }
    }
    let r: CompareResults = serde_json::from_str(&text).expect("results.json parses");
    assert_eq!(r.cases.len(), 2);
    assert_eq!(r.stats.len(), 2);
    // Wall times apart (not a function of the seed): one per run.
    let t: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("timings.json")).unwrap()).unwrap();
    assert_eq!(t.as_array().map(Vec::len), Some(2 * 5));
    assert!(raw.get("timings").is_none());
    r
}

/// The paper's claim: in adversarial light (lamp on the marker, dark surroundings)
/// AAEC keeps the marker detected, Default, metering the dark scene, does not.
fn assert_paper_claim(r: &CompareResults) {
    let rate = |m: ExposureMethod| {
        let c = r
            .cases
            .iter()
            .find(|c| c.method == m && c.lighting == LightingScenario::Adversarial)
            .expect("adversarial case");
        (
            c.static_precision.detection_rate,
            c.motion_tracking.detection_rate,
        )
    };
    let (aaec_static, aaec_motion) = rate(ExposureMethod::Aaec);
    let (def_static, def_motion) = rate(ExposureMethod::Default);
    assert!(
        aaec_static > def_static,
        "static, adversarial: AAEC {aaec_static} vs Default {def_static}"
    );
    assert!(
        aaec_motion > def_motion,
        "motion, adversarial: AAEC {aaec_motion} vs Default {def_motion}"
    );
    // The AAEC run is a real detection run, not an empty one.
    assert!(aaec_static > 0.9, "AAEC static detection {aaec_static}");
}

/// One seed of `seconds` for `methods` in adversarial light, on `jobs` threads.
fn adversarial(
    seed: u64,
    seconds: f64,
    methods: Vec<ExposureMethod>,
    jobs: usize,
) -> CompareOptions {
    CompareOptions {
        seeds: vec![seed],
        seconds,
        methods,
        lightings: vec![LightingScenario::Adversarial],
        jobs,
    }
}

#[test]
fn same_seeds_same_numbers_whatever_the_thread_count() {
    let site = markhold::params::load(Path::new(SITE)).expect("fixture site");
    let methods = vec![ExposureMethod::Aaec, ExposureMethod::Gec];
    let opts = adversarial(3, 1.0, methods, 1);
    let a = run_compare(&site, &opts, &tracing::Span::none()).expect("first run");
    let b = run_compare(
        &site,
        &CompareOptions { jobs: 2, ..opts },
        &tracing::Span::none(),
    )
    .expect("second run");
    assert_eq!(a.results.cases, b.results.cases);
    assert_eq!(a.results.stats, b.results.stats);
    // Frame counts follow --seconds: 1 s at 30 fps.
    assert!(a.series.iter().all(|s| s.samples.len() == 30));
}

/// The paper's ordering in adversarial light, with margins, on a reduced grid (one seed,
/// 8 s): markhold's AAEC keeps the marker (>= 90 % static and moving); AEC and Default,
/// metering the dark surroundings, stay below 5 %; Shim's GEC stays 50 points below AAEC.
#[test]
fn adversarial_light_ordering_with_margins() {
    let site = markhold::params::load(Path::new(SITE)).expect("fixture site");
    let methods = vec![
        ExposureMethod::Aaec,
        ExposureMethod::Gec,
        ExposureMethod::Aec,
        ExposureMethod::Default,
    ];
    let opts = adversarial(1, 8.0, methods, 2);
    let r = run_compare(&site, &opts, &tracing::Span::none())
        .expect("compare")
        .results;
    let rate = |m: ExposureMethod| {
        let c = r.cases.iter().find(|c| c.method == m).expect("case");
        (
            c.static_precision.detection_rate,
            c.motion_tracking.detection_rate,
        )
    };
    let (aaec_s, aaec_m) = rate(ExposureMethod::Aaec);
    eprintln!("AAEC (markhold) static {aaec_s:.3} motion {aaec_m:.3}");
    assert!(aaec_s >= 0.9 && aaec_m >= 0.9, "AAEC {aaec_s} {aaec_m}");
    for m in [ExposureMethod::Aec, ExposureMethod::Default] {
        let (s, mo) = rate(m);
        eprintln!("{m} static {s:.3} motion {mo:.3}");
        assert!(s < 0.05 && mo < 0.05, "{m}: static {s} motion {mo}");
    }
    let (gec_s, gec_m) = rate(ExposureMethod::Gec);
    eprintln!("GEC (Shim) static {gec_s:.3} motion {gec_m:.3}");
    assert!(
        gec_s < aaec_s - 0.5 && gec_m < aaec_m - 0.5,
        "GEC {gec_s} {gec_m}"
    );
}

/// The convergence experiment at the camera's full size (params/pool.toml, 1440x1080),
/// markhold's AAEC, seeds 1 and 2: from 10x too long and 10x too short of where the static
/// run settled, the exposure stays within 5 % of its final value after at most 8 frames in
/// adversarial, normal and low light (measured 6 / 8, 4 / 2, 0 / 4; the full sweep's
/// figures are in docs/results.md). Runs of 3 s: the experiment settles in under 0.3 s.
#[test]
fn aaec_stays_within_5_percent_after_8_frames_at_full_size() {
    let site = markhold::params::load(Path::new("params/pool.toml")).expect("pool site");
    let opts = CompareOptions {
        seeds: vec![1, 2],
        seconds: 3.0,
        methods: vec![ExposureMethod::Aaec],
        lightings: vec![
            LightingScenario::Adversarial,
            LightingScenario::Normal,
            LightingScenario::Low,
        ],
        jobs: 2,
    };
    let r = run_compare(&site, &opts, &tracing::Span::none())
        .expect("compare")
        .results;
    assert_eq!(r.cases.len(), 6);
    for c in &r.cases {
        let cv = &c.convergence;
        let (long, short) = (&cv.from_long, &cv.from_short);
        eprintln!(
            "{} seed {}: from 10x long first {} stays {} frames, from 10x short first {} \
             stays {} (reference {:.0} us)",
            c.lighting,
            c.seed,
            long.first_within_frames,
            long.frames,
            short.first_within_frames,
            short.frames,
            cv.reference_exposure_us
        );
        for s in [long, short] {
            assert!(s.frames <= 8, "{} seed {}: {cv:?}", c.lighting, c.seed);
            assert!(s.settled, "{} seed {}: {cv:?}", c.lighting, c.seed);
        }
    }
}

/// Convergence against the scene's optimum: a method that reaches it reports the frames,
/// a frozen one (GEC as the paper's code ran it: Kp 1e-8) reports "never", in
/// results.json (null) and in the report. Both cases share the scene (adversarial light,
/// seed 1), so one sweep serves both.
#[test]
fn convergence_to_the_optimum_is_reported_and_a_frozen_method_never_gets_there() {
    let site = markhold::params::load(Path::new(SITE)).expect("fixture site");
    let methods = vec![ExposureMethod::Aaec, ExposureMethod::GecPaper];
    let opts = adversarial(1, 3.0, methods, 2);
    let r = run_compare(&site, &opts, &tracing::Span::none())
        .expect("compare")
        .results;
    let case = |m: ExposureMethod| r.cases.iter().find(|c| c.method == m).expect("case");
    let (aaec, gec) = (case(ExposureMethod::Aaec), case(ExposureMethod::GecPaper));
    assert_eq!(aaec.convergence.optimum, gec.convergence.optimum);
    let o = &aaec.convergence.optimum;
    eprintln!("optimum {o:?}");
    assert!(o.m_band_us[0] <= o.m_argmax_us && o.m_argmax_us <= o.m_band_us[1] * 1.03);
    let band = o
        .detection_band_us
        .expect("the marker is seen at some exposure");
    for (m, c) in [("aaec", aaec), ("gec-paper", gec)] {
        for (side, s) in [
            ("long", &c.convergence.from_long),
            ("short", &c.convergence.from_short),
        ] {
            eprintln!(
                "{m} from 10x {side}: to argmax {:?}, to M band {:?}, to detection band {:?}, \
                 final / argmax {:.2}",
                s.frames_to_m_argmax,
                s.frames_to_m_band,
                s.frames_to_detection_band,
                s.final_over_m_argmax
            );
        }
    }
    // markhold's AAEC gets within 5 % of the argmax from both sides, within the run.
    for s in [&aaec.convergence.from_long, &aaec.convergence.from_short] {
        let f = s.frames_to_m_argmax.expect("AAEC reaches the argmax");
        assert!(f < 60, "{f}");
        assert!(s.frames_to_detection_band.is_some());
    }
    // The frozen method stays 10x off: never, though its own "convergence" (to its final
    // value) is immediate.
    for s in [&gec.convergence.from_long, &gec.convergence.from_short] {
        assert_eq!(s.frames_to_m_argmax, None);
        assert_eq!(s.frames_to_m_band, None);
        assert!(s.frames <= 1, "{s:?}");
        let f = s.final_over_m_argmax;
        assert!(!(0.5..=2.0).contains(&f), "{f}");
        let _ = band;
    }
    let report = markhold::sim::compare::report_markdown(&r, &[]);
    let row = report
        .lines()
        .find(|l| l.starts_with("| GEC (paper) |") && l.contains("never"))
        .expect("the frozen method's row says never");
    assert!(row.matches("never").count() >= 4, "{row}");
}
