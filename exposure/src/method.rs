//! The exposure methods markhold can run and, for each, everything the rest of markhold
//! needs to know about it, declared once in [`METHODS`]: its name on the command line and
//! in files, its label in reports and plots, the AAEC paper's figures for it, and how its
//! controller is built. A new method is a variant of [`ExposureMethod`] (with its serde
//! name), its controller, and one row of [`METHODS`]; the simulator's commands, reports
//! and plots read the table.

use crate::{
    Aaec, AaecFallback, AaecPaper, Aec, AecPaper, ExposureConfig, ExposureController,
    ExposureError, ExposureLimits, Gec, GecPaper, MeanAe,
};
use serde::{Deserialize, Serialize};

/// The exposure methods markhold can run (the columns of the paper's tables).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ExposureMethod {
    /// markhold's AAEC: the paper's RoI and metric with a log-domain, bracketing
    /// optimiser and safety nets of its own (`aaec/`).
    Aaec,
    /// Adaptive Active Exposure Control as the paper's code ran it (`aaec_paper.rs`).
    #[serde(rename = "aaec-paper")]
    AaecPaper,
    /// Active exposure control, Zhang, Forster & Scaramuzza 2017.
    Aec,
    /// AEC as the AAEC paper's code ran it (whole frame, fixed step; `aec_paper.rs`).
    #[serde(rename = "aec-paper")]
    AecPaper,
    /// Gamma-based exposure control, Shim et al., with the published constants.
    Gec,
    /// GEC as the AAEC paper's code ran it (its anchors, score, region and Kp 1e-8).
    #[serde(rename = "gec-paper")]
    GecPaper,
    /// A camera's built-in mean-intensity auto exposure ("Default" in the paper).
    Default,
}

/// What the AAEC paper measured with a method (docs/reference/exposure-spec.md, "What the
/// paper measured"), shown beside markhold's figures in `markhold compare`'s report. The
/// paper's figures sit in the rows of the methods as its code ran them; markhold's
/// variants and the official AEC have none.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PaperFigures {
    /// Static marker in a river, 1 minute: det(cov) m^6, detection %, max distance m.
    pub static_precision: Option<(f64, f64, f64)>,
    /// Moving camera, adversarial light only: mean distance and detection, as printed.
    pub motion_adversarial: Option<&'static str>,
    /// Convergence seconds in adversarial, normal and low light.
    pub convergence_s: Option<[f64; 3]>,
}

impl PaperFigures {
    /// A method the paper did not measure.
    pub const NONE: Self = Self {
        static_precision: None,
        motion_adversarial: None,
        convergence_s: None,
    };
}

/// Builds a method's controller from the `[exposure]` section (already validated), for a
/// camera with these limits, starting at this exposure (microseconds).
type Build =
    fn(&ExposureConfig, ExposureLimits, f64) -> Result<Box<dyn ExposureController>, ExposureError>;

/// One exposure method, declared once.
#[derive(Debug, Clone, Copy)]
pub struct MethodInfo {
    pub method: ExposureMethod,
    /// Its name on the command line, in site files and results (serde's name).
    pub name: &'static str,
    /// Other names the command line accepts.
    pub aliases: &'static [&'static str],
    /// The label of its rows and curves in reports and plots.
    pub label: &'static str,
    /// It runs the paper's code (`aaec-paper`, `gec-paper`, `aec-paper`).
    pub paper_code: bool,
    /// What markhold's variant of a published method is, for the report's header (none
    /// for the paper's code and the camera's own AE).
    pub variant_of: Option<&'static str>,
    /// The paper's figures for it.
    pub paper: PaperFigures,
    build: Build,
}

/// Every method, in the order of reports, plots and `--methods`' default.
pub const METHODS: [MethodInfo; 7] = [
    MethodInfo {
        method: ExposureMethod::AaecPaper,
        name: "aaec-paper",
        aliases: &[],
        label: "AAEC (paper)",
        paper_code: true,
        variant_of: None,
        paper: PaperFigures {
            static_precision: Some((1.65e-23, 100.0, 0.0040)),
            motion_adversarial: Some("0.0058 m / 99.32 %"),
            convergence_s: Some([4.0, 3.0, 6.0]),
        },
        build: |cfg, limits, initial_us| {
            let (response, ae) = (cfg.response.load()?, cfg.default.clone());
            boxed(AaecPaper::new(
                cfg.aaec_paper.clone(),
                &response,
                ae,
                limits,
                initial_us,
            ))
        },
    },
    MethodInfo {
        method: ExposureMethod::Aaec,
        name: "aaec",
        aliases: &[],
        label: "AAEC (markhold)",
        paper_code: false,
        variant_of: Some("markhold's AAEC"),
        paper: PaperFigures::NONE,
        build: build_aaec,
    },
    MethodInfo {
        method: ExposureMethod::GecPaper,
        name: "gec-paper",
        aliases: &[],
        label: "GEC (paper)",
        paper_code: true,
        variant_of: None,
        paper: PaperFigures {
            static_precision: Some((1.02e-20, 100.0, 0.0273)),
            motion_adversarial: Some("0.0490 m / 29.29 %"),
            convergence_s: None,
        },
        build: |cfg, limits, initial_us| {
            boxed(GecPaper::new(cfg.gec_paper.clone(), limits, initial_us))
        },
    },
    MethodInfo {
        method: ExposureMethod::Gec,
        name: "gec",
        aliases: &[],
        label: "GEC (Shim)",
        paper_code: false,
        variant_of: Some("GEC with Shim's published constants"),
        paper: PaperFigures::NONE,
        build: |cfg, limits, initial_us| boxed(Gec::new(cfg.gec.clone(), limits, initial_us)),
    },
    MethodInfo {
        method: ExposureMethod::AecPaper,
        name: "aec-paper",
        aliases: &[],
        label: "AEC (paper)",
        paper_code: true,
        variant_of: None,
        paper: PaperFigures {
            static_precision: Some((1.38e-20, 100.0, 0.0598)),
            motion_adversarial: Some("no detection"),
            convergence_s: Some([63.0, 43.0, 72.0]),
        },
        build: |cfg, limits, initial_us| {
            let (response, ae) = (cfg.response.load()?, cfg.default.clone());
            boxed(AecPaper::new(
                cfg.aec_paper.clone(),
                &response,
                ae,
                limits,
                initial_us,
            ))
        },
    },
    MethodInfo {
        method: ExposureMethod::Aec,
        name: "aec",
        aliases: &[],
        label: "AEC (Zhang)",
        paper_code: false,
        variant_of: Some("AEC with its official code's safety nets"),
        paper: PaperFigures::NONE,
        build: |cfg, limits, initial_us| {
            let response = cfg.response.load()?;
            boxed(Aec::new(cfg.aec.clone(), &response, limits, initial_us))
        },
    },
    MethodInfo {
        method: ExposureMethod::Default,
        name: "default",
        aliases: &["mean"],
        label: "Default",
        paper_code: false,
        variant_of: None,
        paper: PaperFigures {
            static_precision: Some((3.82e-20, 99.6, 0.0462)),
            motion_adversarial: Some("no detection"),
            convergence_s: None,
        },
        build: |cfg, limits, initial_us| {
            boxed(MeanAe::new(cfg.default.clone(), limits, initial_us))
        },
    },
];

const fn paper_code_count() -> usize {
    let (mut i, mut n) = (0, 0);
    while i < METHODS.len() {
        if METHODS[i].paper_code {
            n += 1;
        }
        i += 1;
    }
    n
}

impl ExposureMethod {
    /// Every method, in the order of [`METHODS`].
    pub const ALL: [ExposureMethod; METHODS.len()] = {
        let mut all = [ExposureMethod::Default; METHODS.len()];
        let mut i = 0;
        while i < METHODS.len() {
            all[i] = METHODS[i].method;
            i += 1;
        }
        all
    };

    /// The methods that run the paper's code (`aaec-paper`, `gec-paper`, `aec-paper`).
    pub const PAPER_CODE: [ExposureMethod; paper_code_count()] = {
        let mut all = [ExposureMethod::Default; paper_code_count()];
        let (mut i, mut n) = (0, 0);
        while i < METHODS.len() {
            if METHODS[i].paper_code {
                all[n] = METHODS[i].method;
                n += 1;
            }
            i += 1;
        }
        all
    };

    /// Its row of [`METHODS`].
    pub fn info(self) -> &'static MethodInfo {
        METHODS
            .iter()
            .find(|i| i.method == self)
            .expect("every ExposureMethod has a row in METHODS (a unit test checks it)")
    }

    pub fn as_str(self) -> &'static str {
        self.info().name
    }

    /// Every method's name in the order of [`METHODS`], `sep` between two and `last`
    /// before the last one (for help texts: `", "` and `" or "`).
    pub fn names(sep: &str, last: &str) -> String {
        let mut out = String::new();
        for (n, i) in METHODS.iter().enumerate() {
            if n > 0 {
                out.push_str(if n + 1 == METHODS.len() { last } else { sep });
            }
            out.push_str(i.name);
        }
        out
    }

    /// The label of its rows and curves in reports and plots.
    pub fn label(self) -> &'static str {
        self.info().label
    }

    /// Build this method's controller for a camera with `limits`, starting at
    /// `initial_us`, after checking the whole `[exposure]` section.
    pub fn build(
        self,
        cfg: &ExposureConfig,
        limits: ExposureLimits,
        initial_us: f64,
    ) -> Result<Box<dyn ExposureController>, ExposureError> {
        cfg.validate()?;
        (self.info().build)(cfg, limits, initial_us)
    }
}

impl std::fmt::Display for ExposureMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for ExposureMethod {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.to_ascii_lowercase();
        METHODS
            .iter()
            .find(|i| i.name == s || i.aliases.contains(&s.as_str()))
            .map(|i| i.method)
            .ok_or_else(|| {
                format!(
                    "unknown exposure method '{s}': expected one of {}",
                    Self::names(", ", ", ")
                )
            })
    }
}

/// A controller, boxed.
fn boxed(
    c: Result<impl ExposureController + 'static, ExposureError>,
) -> Result<Box<dyn ExposureController>, ExposureError> {
    Ok(Box::new(c?))
}

fn build_aaec(
    cfg: &ExposureConfig,
    limits: ExposureLimits,
    initial_us: f64,
) -> Result<Box<dyn ExposureController>, ExposureError> {
    let response = cfg.response.load()?;
    let fallback: Box<dyn ExposureController> = match cfg.aaec.fallback {
        AaecFallback::Mean => Box::new(MeanAe::new(cfg.default.clone(), limits, initial_us)?),
        AaecFallback::Aec => Box::new(Aec::new(cfg.aec.clone(), &response, limits, initial_us)?),
    };
    boxed(Aaec::new(
        cfg.aaec.clone(),
        response,
        limits,
        initial_us,
        fallback,
    ))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// Every variant, listed by an exhaustive match so that a new one must be added here.
    fn variants() -> Vec<ExposureMethod> {
        use ExposureMethod as M;
        let all = [
            M::Aaec,
            M::AaecPaper,
            M::Aec,
            M::AecPaper,
            M::Gec,
            M::GecPaper,
            M::Default,
        ];
        for m in all {
            match m {
                M::Aaec
                | M::AaecPaper
                | M::Aec
                | M::AecPaper
                | M::Gec
                | M::GecPaper
                | M::Default => {}
            }
        }
        all.to_vec()
    }

    #[test]
    fn every_method_has_one_row_whose_name_is_its_serde_name() {
        for m in variants() {
            assert_eq!(METHODS.iter().filter(|i| i.method == m).count(), 1, "{m:?}");
            let json = serde_json::to_string(&m).unwrap();
            assert_eq!(json, format!("\"{}\"", m.as_str()), "{m:?}");
            assert_eq!(serde_json::from_str::<ExposureMethod>(&json).unwrap(), m);
            assert_eq!(m.as_str().parse::<ExposureMethod>().unwrap(), m);
        }
        assert_eq!(METHODS.len(), variants().len());
    }

    #[test]
    fn names_labels_and_aliases_are_unique() {
        let mut names: Vec<&str> = METHODS.iter().map(|i| i.name).collect();
        names.extend(METHODS.iter().flat_map(|i| i.aliases.iter().copied()));
        let mut labels: Vec<&str> = METHODS.iter().map(|i| i.label).collect();
        for v in [&mut names, &mut labels] {
            let n = v.len();
            v.sort_unstable();
            v.dedup();
            assert_eq!(v.len(), n, "{v:?}");
        }
    }

    #[test]
    fn an_unknown_name_lists_every_method_and_aliases_parse() {
        let e = "Bogus".parse::<ExposureMethod>().unwrap_err();
        assert_eq!(
            e,
            "unknown exposure method 'bogus': expected one of aaec-paper, aaec, gec-paper, gec, aec-paper, aec, default"
        );
        assert_eq!(
            "MEAN".parse::<ExposureMethod>().unwrap(),
            ExposureMethod::Default
        );
    }

    #[test]
    fn paper_code_is_the_paper_code_rows_in_order() {
        assert_eq!(
            ExposureMethod::PAPER_CODE,
            [
                ExposureMethod::AaecPaper,
                ExposureMethod::GecPaper,
                ExposureMethod::AecPaper
            ]
        );
    }
}
