//! Quantiles of the normal, chi-square and Student-t distributions: the bounds of the
//! covariance consistency checks (NEES against chi-square) and `compare`'s confidence
//! intervals and paired t-tests over seeds.
//!
//! Hand-written rather than pulled in from a statistics crate: the normal quantile is
//! Acklam's rational approximation, chi-square's Wilson-Hilferty's, and Student's t comes
//! from the regularized incomplete beta function (a continued fraction, Lentz's method).

/// Upper 95 % quantiles of chi-square with 1 and 3 degrees of freedom.
pub const CHI2_95_DOF1: f64 = 3.841_458_820_694_124;
pub const CHI2_95_DOF3: f64 = 7.814_727_903_251_178;

/// Standard normal quantile (Acklam's rational approximation, relative error < 1.2e-9).
pub fn normal_quantile(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    if p < 0.02425 {
        tail((-2.0 * p.ln()).sqrt())
    } else if p > 1.0 - 0.02425 {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

/// Quantile `p` of chi-square with `dof` degrees of freedom (Wilson-Hilferty; within
/// 0.1 % of the exact value for `dof` >= 30, which a bound on the mean of 30 or more
/// frames has).
pub fn chi2_quantile(p: f64, dof: f64) -> f64 {
    let k = 2.0 / (9.0 * dof);
    dof * (1.0 - k + normal_quantile(p) * k.sqrt()).powi(3)
}

/// Two-sided 95 % interval for the mean of `n` independent chi-square(`dof`) draws:
/// `n` times the mean is chi-square(`n dof`), so the interval is its 2.5 % and 97.5 %
/// quantiles divided by `n`.
pub fn mean_bounds_95(dof: f64, n: u64) -> (f64, f64) {
    let n = n.max(1) as f64;
    (
        chi2_quantile(0.025, n * dof) / n,
        chi2_quantile(0.975, n * dof) / n,
    )
}

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
    fn quantiles_match_tables() {
        // chi-square tables: (p, dof, value).
        for (p, dof, want) in [
            (0.975, 30.0, 46.979),
            (0.025, 30.0, 16.791),
            (0.95, 100.0, 124.342),
            (0.05, 100.0, 77.929),
        ] {
            let got = chi2_quantile(p, dof);
            assert!(
                (got - want).abs() < 1e-3 * want,
                "{p} {dof}: {got} vs {want}"
            );
        }
        assert!((normal_quantile(0.975) - 1.959_964).abs() < 1e-6);
        assert!((normal_quantile(0.01) + 2.326_348).abs() < 1e-6);
        // 300 frames of 3 dof: the mean's standard deviation is sqrt(6 / 300) = 0.141,
        // so about 3 -0.27 / +0.28.
        let (lo, hi) = mean_bounds_95(3.0, 300);
        assert!(
            (2.72..2.74).contains(&lo) && (3.27..3.29).contains(&hi),
            "{lo} {hi}"
        );
    }
}
