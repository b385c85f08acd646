//! Statistics over seeds for `markhold compare`: the mean with a 95 % Student-t confidence
//! interval, and the paired t-test of two methods run on the same seeds.
//!
//! Why t and not a bootstrap: a sweep has 5-10 seeds, and a percentile bootstrap of so few
//! values under-covers (its interval cannot be wider than the values' own range). Why a
//! paired t-test and not Wilcoxon's signed-rank test: with 5 seeds the exact two-sided
//! signed-rank p-value cannot go below 2/2^5 = 0.0625, so no result could ever reach 5 %.
//! The t-distribution is computed here from the regularized incomplete beta function (a
//! continued fraction, Lentz's method) rather than pulled in from a statistics crate.

/// Natural log of the gamma function (Lanczos, g = 7, 9 terms; ~1e-15 relative for x > 0).
fn ln_gamma(x: f64) -> f64 {
    const G: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Reflection: Gamma(x) Gamma(1 - x) = pi / sin(pi x).
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = G[0];
    let t = x + 7.5;
    for (i, g) in G.iter().enumerate().skip(1) {
        a += g / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Continued fraction of the incomplete beta function (modified Lentz).
fn beta_cf(a: f64, b: f64, x: f64) -> f64 {
    const TINY: f64 = 1e-300;
    let (qab, qap, qam) = (a + b, a + 1.0, a - 1.0);
    let mut c = 1.0;
    let mut d = 1.0 - qab * x / qap;
    if d.abs() < TINY {
        d = TINY;
    }
    d = 1.0 / d;
    let mut h = d;
    for m in 1..=300 {
        let m = f64::from(m);
        let m2 = 2.0 * m;
        // One modified-Lentz step: the even then the odd term of the fraction.
        let mut lentz = |aa: f64| {
            d = 1.0 + aa * d;
            if d.abs() < TINY {
                d = TINY;
            }
            c = 1.0 + aa / c;
            if c.abs() < TINY {
                c = TINY;
            }
            d = 1.0 / d;
            d * c
        };
        h *= lentz(m * (b - m) * x / ((qam + m2) * (a + m2)));
        let del = lentz(-(a + m) * (qab + m) * x / ((a + m2) * (qap + m2)));
        h *= del;
        if (del - 1.0).abs() < 1e-15 {
            break;
        }
    }
    h
}

/// Regularized incomplete beta function I_x(a, b), x in [0, 1].
fn inc_beta(a: f64, b: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x >= 1.0 {
        return 1.0;
    }
    let ln_front = ln_gamma(a + b) - ln_gamma(a) - ln_gamma(b) + a * x.ln() + b * (1.0 - x).ln();
    let front = ln_front.exp();
    if x < (a + 1.0) / (a + b + 2.0) {
        front * beta_cf(a, b, x) / a
    } else {
        1.0 - front * beta_cf(b, a, 1.0 - x) / b
    }
}

/// Two-sided tail probability P(|T| >= |t|) of Student's t with `df` degrees of freedom.
pub fn t_two_sided_p(t: f64, df: f64) -> f64 {
    if t.is_infinite() {
        return 0.0;
    }
    inc_beta(0.5 * df, 0.5, df / (df + t * t))
}

/// The t value with two-sided tail probability `p` (e.g. 0.05 gives the 97.5 % quantile),
/// by bisection on [`t_two_sided_p`].
pub fn t_quantile_two_sided(p: f64, df: f64) -> f64 {
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    while t_two_sided_p(hi, df) > p {
        hi *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if t_two_sided_p(mid, df) > p {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-13 * hi {
            break;
        }
    }
    0.5 * (lo + hi)
}

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
    fn t_distribution_against_closed_forms_and_tables() {
        // df = 1 is Cauchy: P(|T| > 1) = 1/2.
        close(t_two_sided_p(1.0, 1.0), 0.5, 1e-12);
        // df = 2: F(t) = 1/2 + t / (2 sqrt(2 + t^2)), so P(|T| > 2) = 1 - 2/sqrt(6).
        close(t_two_sided_p(2.0, 2.0), 1.0 - 2.0 / 6f64.sqrt(), 1e-12);
        close(t_two_sided_p(0.0, 7.0), 1.0, 1e-12);
        // Printed 97.5 % quantiles.
        close(t_quantile_two_sided(0.05, 1.0), 12.706_204_736, 1e-6);
        close(t_quantile_two_sided(0.05, 4.0), 2.776_445_105, 1e-8);
        close(t_quantile_two_sided(0.05, 9.0), 2.262_157_163, 1e-8);
        close(t_quantile_two_sided(0.05, 1000.0), 1.962_339_0, 1e-6);
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
