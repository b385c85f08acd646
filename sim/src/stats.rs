//! Statistics over seeds for `markhold compare`: the mean with a 95 % Student-t confidence
//! interval, and the paired t-test of two methods run on the same seeds.
//!
//! Why t and not a bootstrap: a sweep has 5-10 seeds, and a percentile bootstrap of so few
//! values under-covers (its interval cannot be wider than the values' own range). Why a
//! paired t-test and not Wilcoxon's signed-rank test: with 5 seeds the exact two-sided
//! signed-rank p-value cannot go below 2/2^5 = 0.0625, so no result could ever reach 5 %.
//! The t-distribution itself is markhold-geometry's ([`markhold_geometry::stats`]).

use markhold_geometry::stats::{t_quantile_two_sided, t_two_sided_p};

/// Mean, sample standard deviation and 95 % t confidence interval of `v`. The sd and the
/// interval need two values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeanCi {
    pub mean: f64,
    pub sd: Option<f64>,
    pub ci95: Option<(f64, f64)>,
}

pub fn mean_ci95(v: &[f64]) -> Option<MeanCi> {
    if v.is_empty() {
        return None;
    }
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    if v.len() < 2 {
        return Some(MeanCi {
            mean,
            sd: None,
            ci95: None,
        });
    }
    let sd = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    let h = t_quantile_two_sided(0.05, n - 1.0) * sd / n.sqrt();
    Some(MeanCi {
        mean,
        sd: Some(sd),
        ci95: Some((mean - h, mean + h)),
    })
}

/// A paired t-test of `a - b` over the same seeds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Paired {
    pub n: usize,
    pub mean_diff: f64,
    pub ci95: Option<(f64, f64)>,
    pub t: Option<f64>,
    /// Two-sided p-value of "mean difference 0". None with fewer than two pairs, or when
    /// every difference is 0; 0 when every difference is the same non-zero value.
    pub p: Option<f64>,
}

pub fn paired_t(diffs: &[f64]) -> Option<Paired> {
    let m = mean_ci95(diffs)?;
    let n = diffs.len();
    let (t, p) = match m.sd {
        None => (None, None),
        Some(0.0) => {
            if m.mean == 0.0 {
                (None, None)
            } else {
                (Some(m.mean.signum() * f64::INFINITY), Some(0.0))
            }
        }
        Some(sd) => {
            let t = m.mean / (sd / (n as f64).sqrt());
            (Some(t), Some(t_two_sided_p(t, n as f64 - 1.0)))
        }
    };
    Some(Paired {
        n,
        mean_diff: m.mean,
        ci95: m.ci95,
        t,
        p,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) {
        assert!((a - b).abs() <= tol, "{a} vs {b}");
    }

    #[test]
    fn ci_of_a_hand_computed_case() {
        // 1..5: mean 3, sd sqrt(2.5), half-width 2.776445105 * sqrt(2.5) / sqrt(5).
        let m = mean_ci95(&[1.0, 2.0, 3.0, 4.0, 5.0]).unwrap();
        close(m.mean, 3.0, 1e-15);
        close(m.sd.unwrap(), 2.5f64.sqrt(), 1e-15);
        let h = 2.776_445_105 * 0.5f64.sqrt();
        let (lo, hi) = m.ci95.unwrap();
        close(lo, 3.0 - h, 1e-8);
        close(hi, 3.0 + h, 1e-8);
        let one = mean_ci95(&[4.0]).unwrap();
        assert_eq!((one.mean, one.sd, one.ci95), (4.0, None, None));
        assert!(mean_ci95(&[]).is_none());
    }

    #[test]
    fn paired_test_of_a_hand_computed_case() {
        // Differences 1, 3 (n = 2): mean 2, sd sqrt(2), t = 2 / (sqrt(2)/sqrt(2)) = 2, df 1:
        // p = 1 - 2 atan(2) / pi.
        let p = paired_t(&[1.0, 3.0]).unwrap();
        close(p.t.unwrap(), 2.0, 1e-12);
        close(
            p.p.unwrap(),
            1.0 - 2.0 * 2f64.atan() / std::f64::consts::PI,
            1e-12,
        );
        // Differences 1, 2, 3 (df 2): mean 2, sd 1, t = 2 sqrt(3); p = 1 - t / sqrt(2 + t^2).
        let p = paired_t(&[1.0, 2.0, 3.0]).unwrap();
        let t = 2.0 * 3f64.sqrt();
        close(p.t.unwrap(), t, 1e-12);
        close(p.p.unwrap(), 1.0 - t / (2.0 + t * t).sqrt(), 1e-12);
        // The same difference on every seed: certain; no difference at all: no test.
        assert_eq!(paired_t(&[0.5, 0.5, 0.5]).unwrap().p, Some(0.0));
        assert_eq!(paired_t(&[0.0, 0.0]).unwrap().p, None);
        assert_eq!(paired_t(&[1.0]).unwrap().p, None);
    }
}
