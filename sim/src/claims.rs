//! The AAEC paper's claims as paired comparisons over seeds: for each claim, each AAEC
//! variant in the sweep against each other method, the per-seed difference (same seed,
//! same world) with its mean, 95 % confidence interval and paired-t p-value
//! ([`super::stats`]).

use markhold_exposure::ExposureMethod;
use markhold_hil::scene::LightingScenario;
use serde::{Deserialize, Serialize};

use super::compare::{metrics, CaseResult, CompareHeader};
use super::stats::paired_t;

/// Which way a metric is better.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Better {
    Higher,
    Lower,
}

/// The scale the difference is taken on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Scale {
    Linear,
    /// Determinants span orders of magnitude: their log10 is compared.
    Log10,
}

/// What the test says about the claim.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    /// The AAEC variant is better on average and p < 0.05, or it has the metric on every
    /// seed and the other method on none (it sees the marker, the other does not).
    Holds,
    /// Better on average, p >= 0.05 (or too few seeds for a test).
    NotSignificant,
    /// Worse on average (any p).
    Against,
    /// No seed where the AAEC variant has the metric.
    Untested,
}

/// One claim, one AAEC variant against one other method.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ClaimTest {
    /// The claim in words.
    pub claim: String,
    pub lighting: LightingScenario,
    /// The metric key (`experiment.metric`, as in `stats`).
    pub metric: String,
    pub better: Better,
    pub scale: Scale,
    pub method: ExposureMethod,
    pub other: ExposureMethod,
    /// Seeds where both have the metric (the pairs).
    pub n: usize,
    /// Seeds where only `method` / only `other` has it (e.g. only it detects the marker).
    pub method_only: usize,
    pub other_only: usize,
    /// Mean of method - other over the pairs, on `scale`, and its 95 % interval.
    pub mean_diff: Option<f64>,
    pub ci95_low: Option<f64>,
    pub ci95_high: Option<f64>,
    /// Two-sided paired-t p-value of "no difference".
    pub p: Option<f64>,
    pub verdict: Verdict,
}

/// (claim, metric, better, scale, lightings).
type ClaimDef = (
    &'static str,
    &'static str,
    Better,
    Scale,
    &'static [LightingScenario],
);

const ADV: &[LightingScenario] = &[LightingScenario::Adversarial];
const PAPER_LIGHTS: &[LightingScenario] = &[
    LightingScenario::Adversarial,
    LightingScenario::Normal,
    LightingScenario::Low,
];

/// The paper's claims: AAEC first in adversarial light on detection, on the determinant
/// of the static positions and on the distance to the trajectory; AAEC converges faster
/// (all three paper lightings); AAEC holds station with the smallest determinant.
pub const CLAIMS: &[ClaimDef] = &[
    (
        "detects the marker more often, static",
        "static.detection_rate",
        Better::Higher,
        Scale::Linear,
        ADV,
    ),
    (
        "detects the marker more often, moving",
        "motion.detection_rate",
        Better::Higher,
        Scale::Linear,
        ADV,
    ),
    (
        "smaller det(cov) of static positions",
        "static.position_cov_det_m6",
        Better::Lower,
        Scale::Log10,
        ADV,
    ),
    (
        "smaller distance to the trajectory",
        "motion.mean_distance_to_trajectory_m",
        Better::Lower,
        Scale::Linear,
        ADV,
    ),
    (
        "converges faster from 10x long",
        "convergence.long.seconds",
        Better::Lower,
        Scale::Linear,
        PAPER_LIGHTS,
    ),
    (
        "converges faster from 10x short",
        "convergence.short.seconds",
        Better::Lower,
        Scale::Linear,
        PAPER_LIGHTS,
    ),
    (
        "smaller det(cov) holding station",
        "station.position_cov_det_m6",
        Better::Lower,
        Scale::Log10,
        PAPER_LIGHTS,
    ),
];

const AAEC: [ExposureMethod; 2] = [ExposureMethod::AaecPaper, ExposureMethod::Aaec];

fn value(c: &CaseResult, key: &str, scale: Scale) -> Option<f64> {
    let v = metrics(c).into_iter().find(|(k, _)| *k == key)?.1?;
    match scale {
        Scale::Linear => Some(v),
        Scale::Log10 => (v > 0.0).then(|| v.log10()),
    }
}

/// Every claim for every AAEC variant x other method x lighting the sweep holds.
pub fn tests(h: &CompareHeader, cases: &[CaseResult]) -> Vec<ClaimTest> {
    let mut out = Vec::new();
    for &(claim, key, better, scale, lights) in CLAIMS {
        for &l in lights.iter().filter(|l| h.lightings.contains(l)) {
            for &m in AAEC.iter().filter(|m| h.methods.contains(m)) {
                for &o in h.methods.iter().filter(|o| !AAEC.contains(o)) {
                    out.push(one(h, cases, (claim, key, better, scale), l, m, o));
                }
            }
        }
    }
    out
}

fn one(
    h: &CompareHeader,
    cases: &[CaseResult],
    (claim, key, better, scale): (&str, &str, Better, Scale),
    l: LightingScenario,
    m: ExposureMethod,
    o: ExposureMethod,
) -> ClaimTest {
    let get = |method, seed| {
        cases
            .iter()
            .find(|c| c.method == method && c.lighting == l && c.seed == seed)
            .and_then(|c| value(c, key, scale))
    };
    let (mut diffs, mut method_only, mut other_only) = (Vec::new(), 0, 0);
    for &seed in &h.seeds {
        match (get(m, seed), get(o, seed)) {
            (Some(a), Some(b)) => diffs.push(a - b),
            (Some(_), None) => method_only += 1,
            (None, Some(_)) => other_only += 1,
            (None, None) => {}
        }
    }
    let t = paired_t(&diffs);
    let sign = match better {
        Better::Higher => 1.0,
        Better::Lower => -1.0,
    };
    let verdict = match t {
        _ if diffs.is_empty() && method_only == 0 => Verdict::Untested,
        None if other_only == 0 => Verdict::Holds,
        None => Verdict::Against,
        Some(t) if sign * t.mean_diff < 0.0 => Verdict::Against,
        Some(t) if sign * t.mean_diff > 0.0 && t.p.is_some_and(|p| p < 0.05) => Verdict::Holds,
        Some(_) => Verdict::NotSignificant,
    };
    ClaimTest {
        claim: claim.to_string(),
        lighting: l,
        metric: key.to_string(),
        better,
        scale,
        method: m,
        other: o,
        n: diffs.len(),
        method_only,
        other_only,
        mean_diff: t.map(|t| t.mean_diff),
        ci95_low: t.and_then(|t| t.ci95).map(|c| c.0),
        ci95_high: t.and_then(|t| t.ci95).map(|c| c.1),
        p: t.and_then(|t| t.p),
        verdict,
    }
}
