//! `markhold compare --shard I/N` and `markhold compare merge`: a sweep cut into N
//! deterministic slices that a scheduler (SLURM job array, Kubernetes Indexed Job,
//! `xargs -P`) runs anywhere, and merged into the outputs of one unsharded run.
//!
//! The unit of a slice is a case (method x lighting x seed with its five runs); case k of
//! the sweep (in results.json order) goes to shard k mod N + 1, so every shard gets a mix
//! of methods and lightings. A shard writes `shard-I-of-N.json` (written to a temporary
//! name and renamed: a killed task leaves no file), holding what it ran, the sweep's
//! fingerprint, its cases, the first seed's series (the plots) and its wall times. Merge
//! puts the cases back in sweep order and goes through the same [`assemble`] and
//! [`write_outputs`] as an unsharded run; serde_json's `float_roundtrip` makes every
//! number come back bit for bit, so results.json is the same byte for byte.

use std::collections::BTreeMap;
use std::io::Read as _;
use std::path::{Path, PathBuf};

use crate::error::{ensure, Required, SimError, StepContext};
use serde::{Deserialize, Serialize};
use tracing::Span;

use super::{
    assemble, run_cases, CaseKey, CaseResult, CompareHeader, CompareOptions, CompareOutput,
    RunSeries, RunTiming,
};
use markhold_core::params::LoadedSite;

/// Version of the shard file layout.
pub const FORMAT: u32 = 1;
/// The most slices a sweep is cut into.
pub const MAX_SHARDS: u32 = 10_000;
/// The largest shard file read (its series are the first seed's runs).
pub const MAX_SHARD_BYTES: u64 = 256 << 20;

/// `--shard I/N`: the I-th (1-based) of N slices.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    pub index: u32,
    pub count: u32,
}

impl std::str::FromStr for Shard {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("{s:?}: expected I/N with 1 <= I <= N <= {MAX_SHARDS} (e.g. 2/8)");
        let (i, n) = s.split_once('/').ok_or_else(bad)?;
        let index: u32 = i.trim().parse().map_err(|_| bad())?;
        let count: u32 = n.trim().parse().map_err(|_| bad())?;
        let shard = Self { index, count };
        if !shard.valid() {
            return Err(bad());
        }
        Ok(shard)
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

impl Shard {
    /// 1 <= index <= count <= [`MAX_SHARDS`].
    pub fn valid(&self) -> bool {
        self.index >= 1 && self.index <= self.count && self.count <= MAX_SHARDS
    }

    /// The cases of the sweep this shard runs.
    pub fn cases(&self, opts: &CompareOptions) -> Vec<CaseKey> {
        opts.cases()
            .into_iter()
            .enumerate()
            .filter(|(k, _)| *k as u64 % u64::from(self.count) == u64::from(self.index - 1))
            .map(|(_, c)| c)
            .collect()
    }

    pub fn file_name(&self) -> String {
        format!("shard-{}-of-{}.json", self.index, self.count)
    }
}

/// What defines a sweep: two shards merge only if these are equal.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Sweep {
    pub header: CompareHeader,
    /// FNV-1a 64 of the site as loaded (every key, defaults filled in), hex.
    pub site_content: String,
    /// markhold's version and FNV-1a 64 of the executable that ran the shard, hex.
    pub build: String,
}

impl Sweep {
    pub fn of(site: &LoadedSite, opts: &CompareOptions) -> Result<Self, SimError> {
        let site_json =
            serde_json::to_string(&site.site).step(|| "serializing the site".to_string())?;
        Ok(Self {
            header: CompareHeader::of(site, opts),
            site_content: format!("{:016x}", fnv1a(FNV_OFFSET, site_json.as_bytes())),
            build: build_id()?,
        })
    }

    /// The fields where two sweeps differ, with both values (the site file's path may
    /// differ: the same site can sit at different paths on different machines).
    fn differences(&self, o: &Self) -> Vec<String> {
        let mut d = Vec::new();
        let (a, b) = (&self.header, &o.header);
        let mut cmp = |name: &str, x: String, y: String| {
            if x != y {
                d.push(format!("{name} {x} vs {y}"));
            }
        };
        cmp("site", a.site.clone(), b.site.clone());
        cmp(
            "site content",
            self.site_content.clone(),
            o.site_content.clone(),
        );
        cmp(
            "image",
            format!("{}x{}", a.width_px, a.height_px),
            format!("{}x{}", b.width_px, b.height_px),
        );
        cmp("fps", a.fps.to_string(), b.fps.to_string());
        cmp("seconds", a.seconds.to_string(), b.seconds.to_string());
        cmp("seeds", format!("{:?}", a.seeds), format!("{:?}", b.seeds));
        cmp(
            "methods",
            format!("{:?}", a.methods),
            format!("{:?}", b.methods),
        );
        cmp(
            "lightings",
            format!("{:?}", a.lightings),
            format!("{:?}", b.lightings),
        );
        cmp("build", self.build.clone(), o.build.clone());
        d
    }
}

/// `shard-I-of-N.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ShardFile {
    pub format: u32,
    pub shard: Shard,
    pub sweep: Sweep,
    pub cases: Vec<CaseResult>,
    /// The runs of the sweep's first seed (what the plots draw).
    pub series: Vec<RunSeries>,
    pub timings: Vec<RunTiming>,
}

const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;

fn fnv1a(mut h: u64, bytes: &[u8]) -> u64 {
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// markhold's version and a hash of the running executable: shards of different builds
/// may give different numbers, so they do not merge.
fn build_id() -> Result<String, SimError> {
    let exe = std::env::current_exe().step(|| "finding the markhold executable".to_string())?;
    let mut f = std::fs::File::open(&exe).step(|| format!("reading {}", exe.display()))?;
    let mut h = FNV_OFFSET;
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f
            .read(&mut buf)
            .step(|| format!("reading {}", exe.display()))?;
        if n == 0 {
            break;
        }
        h = fnv1a(h, &buf[..n]);
    }
    Ok(format!("{} {h:016x}", env!("CARGO_PKG_VERSION")))
}

/// Write a shard's file into `dir` (created if missing); returns its path.
pub fn write_shard(dir: &Path, file: &ShardFile) -> Result<PathBuf, SimError> {
    std::fs::create_dir_all(dir).step(|| format!("creating --out {}", dir.display()))?;
    let path = dir.join(file.shard.file_name());
    let tmp = dir.join(format!(".{}.partial", file.shard.file_name()));
    let json = serde_json::to_string(file).step(|| "serializing the shard".to_string())?;
    std::fs::write(&tmp, json).step(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, &path)
        .step(|| format!("renaming {} to {}", tmp.display(), path.display()))?;
    Ok(path)
}

/// Is `name` a shard file name (`shard-I-of-N.json`)?
fn is_shard_name(name: &str) -> bool {
    name.strip_prefix("shard-")
        .and_then(|r| r.strip_suffix(".json"))
        .and_then(|r| r.split_once("-of-"))
        .is_some_and(|(i, n)| {
            !i.is_empty()
                && !n.is_empty()
                && i.bytes().all(|b| b.is_ascii_digit())
                && n.bytes().all(|b| b.is_ascii_digit())
        })
}

/// Every shard file in `dirs`, read and parsed, sorted by path.
fn read_shards(dirs: &[PathBuf]) -> Result<Vec<(PathBuf, ShardFile)>, SimError> {
    let mut paths = Vec::new();
    for d in dirs {
        let entries =
            std::fs::read_dir(d).step(|| format!("reading shard folder {}", d.display()))?;
        let before = paths.len();
        for e in entries {
            let e = e.step(|| format!("reading shard folder {}", d.display()))?;
            if e.file_name().to_str().is_some_and(is_shard_name) {
                paths.push(e.path());
            }
        }
        ensure(paths.len() > before, || SimError::Run {
            reason: format!(
                "{}: no shard files (shard-I-of-N.json, written by markhold compare --shard I/N)",
                d.display()
            ),
        })?;
    }
    paths.sort();
    let mut out = Vec::with_capacity(paths.len());
    for p in paths {
        // Regular files of bounded size only: not a FIFO (it would wait for a writer), not
        // a link to a device.
        let text = markhold_config::read_regular(&p, MAX_SHARD_BYTES)
            .step(|| format!("reading {}", p.display()))?;
        let f: ShardFile = serde_json::from_str(&text)
            .step(|| format!("{}: not a markhold compare shard file", p.display()))?;
        ensure(f.format == FORMAT, || SimError::Run {
            reason: format!(
                "{}: shard file format {} (this markhold reads {FORMAT})",
                p.display(),
                f.format
            ),
        })?;
        check_values(&f).map_err(|e| SimError::Run {
            reason: format!("{}: {e}", p.display()),
        })?;
        let expect = f.shard.file_name();
        ensure(
            p.file_name().and_then(|n| n.to_str()) == Some(expect.as_str()),
            || SimError::Run {
                reason: format!(
                    "{}: holds shard {} (file name {expect})",
                    p.display(),
                    f.shard
                ),
            },
        )?;
        out.push((p, f));
    }
    Ok(out)
}

/// A shard's numbers within what a sweep can produce; the error names the field and
/// the value.
fn check_values(f: &ShardFile) -> Result<(), String> {
    use super::{MAX_RUN_SECONDS, MAX_SEEDS};
    let bad = |field: &str, v: &dyn std::fmt::Display, want: &str| {
        Err(format!("{field} = {v}: expected {want}"))
    };
    if !f.shard.valid() {
        return bad(
            "shard",
            &f.shard,
            &format!("I/N with 1 <= I <= N <= {MAX_SHARDS}"),
        );
    }
    let h = &f.sweep.header;
    if !(h.fps > 0.0 && h.fps <= 500.0) {
        return bad("sweep.header.fps", &h.fps, "frames per second in (0, 500]");
    }
    if !(h.seconds > 0.0 && h.seconds <= MAX_RUN_SECONDS) {
        return bad(
            "sweep.header.seconds",
            &h.seconds,
            &format!("seconds in (0, {MAX_RUN_SECONDS}]"),
        );
    }
    if h.seeds.is_empty() || h.seeds.len() > MAX_SEEDS {
        return bad(
            "sweep.header.seeds",
            &h.seeds.len(),
            &format!("1..{MAX_SEEDS} seeds"),
        );
    }
    if !(16..=8192).contains(&h.width_px) || !(16..=8192).contains(&h.height_px) {
        return bad(
            "sweep.header.width_px x height_px",
            &format!("{}x{}", h.width_px, h.height_px),
            "16..8192 pixels each",
        );
    }
    let max_frames = (h.seconds * h.fps).ceil() as u64 + 1;
    f.cases.iter().try_for_each(|c| check_case(c, max_frames))
}

/// One case's numbers: rates in 0..1, sizes finite and not negative, frame counts
/// within the run.
fn check_case(c: &CaseResult, max_frames: u64) -> Result<(), String> {
    let bad = |field: &str, v: &dyn std::fmt::Display, want: &str| {
        Err(format!("{field} = {v}: expected {want}"))
    };
    {
        let at = |field: &str| {
            format!(
                "case {} / {} / seed {}: {field}",
                c.method, c.lighting, c.seed
            )
        };
        let rate = |field: &str, v: f64| {
            if (0.0..=1.0).contains(&v) {
                Ok(())
            } else {
                bad(&at(field), &v, "a rate in 0..1")
            }
        };
        let non_neg = |field: &str, v: f64| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                bad(&at(field), &v, "a finite number >= 0")
            }
        };
        let opt = |field: &str, v: Option<f64>| v.map_or(Ok(()), |v| non_neg(field, v));
        let frames = |field: &str, v: u64| {
            if v <= max_frames {
                Ok(())
            } else {
                bad(
                    &at(field),
                    &v,
                    &format!("at most {max_frames} frames (seconds x fps)"),
                )
            }
        };
        let (m, st, cv) = (&c.motion_tracking, &c.station_keeping, &c.convergence);
        rate("motion_tracking.detection_rate", m.detection_rate)?;
        rate("station_keeping.detection_rate", st.detection_rate)?;
        frames("motion_tracking.frames", m.frames)?;
        frames("station_keeping.frames", st.frames)?;
        non_neg("motion_tracking.speed_mps", m.speed_mps)?;
        non_neg("motion_tracking.span_m", m.span_m)?;
        opt(
            "motion_tracking.mean_distance_to_trajectory_m",
            m.mean_distance_to_trajectory_m,
        )?;
        opt("motion_tracking.mean_error_m", m.mean_error_m)?;
        non_neg("station_keeping.position_rms_m", st.position_rms_m)?;
        non_neg(
            "station_keeping.final_position_error_m",
            st.final_position_error_m,
        )?;
        opt(
            "station_keeping.position_cov_det_m6",
            st.position_cov_det_m6,
        )?;
        opt(
            "station_keeping.measured_position_cov_det_m6",
            st.measured_position_cov_det_m6,
        )?;
        let sp = &c.static_precision;
        rate("static_precision.detection_rate", sp.detection_rate)?;
        frames("static_precision.frames", sp.frames)?;
        opt(
            "static_precision.position_cov_det_m6",
            sp.position_cov_det_m6,
        )?;
        opt("static_precision.max_distance_m", sp.max_distance_m)?;
        opt("static_precision.mean_bias_m", sp.mean_bias_m)?;
        non_neg("static_precision.final_exposure_us", sp.final_exposure_us)?;
        non_neg(
            "convergence.reference_exposure_us",
            cv.reference_exposure_us,
        )?;
        for (name, s) in [("from_long", &cv.from_long), ("from_short", &cv.from_short)] {
            let f = |k: &str| format!("convergence.{name}.{k}");
            rate(&f("detection_rate"), s.detection_rate)?;
            frames(&f("frames"), s.frames)?;
            frames(&f("first_within_frames"), s.first_within_frames)?;
            non_neg(&f("seconds"), s.seconds)?;
            non_neg(&f("first_within_seconds"), s.first_within_seconds)?;
            non_neg(&f("initial_exposure_us"), s.initial_exposure_us)?;
            non_neg(&f("final_exposure_us"), s.final_exposure_us)?;
            non_neg(&f("final_over_reference"), s.final_over_reference)?;
        }
    }
    Ok(())
}

/// Refuse shards of different sweeps or shard counts, duplicates and missing shards.
fn check_complete(shards: &[(PathBuf, ShardFile)]) -> Result<(), SimError> {
    let Some((p0, f0)) = shards.first() else {
        return Err(SimError::Run {
            reason: "no shard files given".to_string(),
        });
    };
    for (p, f) in &shards[1..] {
        let d = f0.sweep.differences(&f.sweep);
        ensure(d.is_empty(), || SimError::Run {
            reason: format!(
                "shards of different sweeps: {} and {} differ in {}",
                p0.display(),
                p.display(),
                d.join("; ")
            ),
        })?;
        ensure(f.shard.count == f0.shard.count, || SimError::Run {
            reason: format!(
                "shards of different cuts of the sweep: {} is one of {} shards, {} one of {}",
                p0.display(),
                f0.shard.count,
                p.display(),
                f.shard.count
            ),
        })?;
    }
    let n = f0.shard.count;
    let mut seen: BTreeMap<u32, &Path> = BTreeMap::new();
    for (p, f) in shards {
        if let Some(other) = seen.insert(f.shard.index, p) {
            return Err(SimError::Run {
                reason: format!(
                    "duplicate shard {}: {} and {} (keep one)",
                    f.shard,
                    other.display(),
                    p.display()
                ),
            });
        }
    }
    let missing: Vec<String> = (1..=n)
        .filter(|i| !seen.contains_key(i))
        .map(|i| format!("{i}/{n}"))
        .collect();
    ensure(missing.is_empty(), || SimError::Run {
        reason: format!(
            "missing shard(s) {} of {n}: rerun each with markhold compare --shard I/{n} and the \
         same options",
            missing.join(", ")
        ),
    })?;
    Ok(())
}

/// Merge the shard files in `dirs` into the output of the unsharded sweep.
pub fn merge(dirs: &[PathBuf]) -> Result<CompareOutput, SimError> {
    let shards = read_shards(dirs)?;
    check_complete(&shards)?;
    let Some((_, first)) = shards.first() else {
        return Err(SimError::Run {
            reason: "no shard files given".to_string(),
        });
    };
    let h = first.sweep.header.clone();
    let opts = CompareOptions {
        seeds: h.seeds.clone(),
        seconds: h.seconds,
        methods: h.methods.clone(),
        lightings: h.lightings.clone(),
        jobs: 1,
    };
    let key = |c: &CaseResult| (c.method, c.lighting, c.seed);
    let mut by_key: BTreeMap<String, CaseResult> = BTreeMap::new();
    let mut series = Vec::new();
    let mut timings = Vec::new();
    for (p, f) in shards {
        for c in f.cases {
            let k = format!("{:?}", key(&c));
            ensure(!by_key.contains_key(&k), || SimError::Run {
                reason: format!(
                    "{}: case {} / {} / seed {} is in two shards",
                    p.display(),
                    c.method,
                    c.lighting,
                    c.seed
                ),
            })?;
            by_key.insert(k, c);
        }
        series.extend(f.series);
        timings.extend(f.timings);
    }
    let mut cases = Vec::with_capacity(by_key.len());
    for c in opts.cases() {
        let k = format!("{:?}", (c.method, c.lighting, c.seed));
        let r = by_key.remove(&k).required(|| {
            format!(
                "no shard holds case {} / {} / seed {}",
                c.method, c.lighting, c.seed
            )
        })?;
        cases.push(r);
    }
    // Sweep order for the series and timings too, whatever order the shards came in.
    let order = |m, l, s| {
        opts.cases()
            .iter()
            .position(|c| c.method == m && c.lighting == l && c.seed == s)
    };
    series.sort_by_key(|s| (order(s.method, s.lighting, s.seed), s.kind as u8));
    timings.sort_by_key(|s| (order(s.method, s.lighting, s.seed), s.kind as u8));
    Ok(CompareOutput {
        results: assemble(h, cases),
        series,
        timings,
    })
}

/// `--shard I/N`: run the slice, write DIR/shard-I-of-N.json.
pub(super) fn run_shard(
    site: &LoadedSite,
    opts: &CompareOptions,
    shard: Shard,
    dir: &std::path::Path,
    bar: &Span,
) -> Result<(), SimError> {
    let sweep = Sweep::of(site, opts)?;
    let cases = shard.cases(opts);
    let run = run_cases(site, opts, &cases, bar)?;
    let first_seed = opts.seeds.first().copied();
    let file = ShardFile {
        format: FORMAT,
        shard,
        sweep,
        cases: run.cases,
        series: run
            .series
            .into_iter()
            .filter(|s| Some(s.seed) == first_seed)
            .collect(),
        timings: run.timings,
    };
    let path = write_shard(dir, &file)?;
    markhold_core::outln!(
        "markhold compare --shard {shard}: {} of {} cases ({} runs of {} s) on {}; wrote {}",
        cases.len(),
        opts.cases().len(),
        5 * cases.len(),
        opts.seconds,
        site.site.site.name,
        path.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shard_arguments_and_slices() {
        assert_eq!("2/3".parse::<Shard>(), Ok(Shard { index: 2, count: 3 }));
        for bad in ["0/3", "4/3", "3", "a/3", "1/0", ""] {
            assert!(bad.parse::<Shard>().is_err(), "{bad}");
        }
        let opts = CompareOptions {
            seeds: vec![1, 2],
            ..CompareOptions::default()
        };
        let all = opts.cases();
        let mut union = Vec::new();
        for i in 1..=5 {
            union.extend(Shard { index: i, count: 5 }.cases(&opts));
        }
        assert_eq!(union.len(), all.len());
        for c in &all {
            assert_eq!(union.iter().filter(|u| *u == c).count(), 1);
        }
        assert!(is_shard_name("shard-12-of-40.json"));
        assert!(!is_shard_name("shard--of-3.json"));
        assert!(!is_shard_name(".shard-1-of-3.json.partial"));
    }
}
