//! The sensor: electrons with shot and read noise, full-well clip, analog gain, the
//! camera response and 8-bit quantization.
//!
//! Noise is added in the square-root domain: for a mean of `m` electrons and read noise
//! `sigma_r`, `s = sqrt(m + sigma_r^2) + g / 2` with `g` standard normal has, back in
//! electrons (`e = s^2 - sigma_r^2`), mean about `m` and variance about `m + sigma_r^2`:
//! shot noise (Poisson, Gaussian approximation) plus read noise, in one square root. The
//! response table is indexed by `s` directly, so a pixel costs one square root, one
//! multiply-add and two table reads.

use markhold_exposure::{Response, ResponseModel};

/// Entries of the response table over `s` in [0, sqrt(full scale + sigma_r^2)].
pub(crate) const RESPONSE_LUT_LEN: usize = 1 << 12;
/// Entries of the Gaussian table (power of two: indexed with a mask). 16 KB: it stays in
/// L1 beside the response table while a frame renders.
const GAUSS_LOG2: u32 = 12;
/// Samples in each of the two noise fields the fast renderer reads rows from (512 KB of
/// i16 each). A row adds windows of both at two random offsets: with one field, a row
/// repeated a shifted window of another with a probability of about 2 width / NOISE_LEN
/// (1 % at 1440 pixels, a dozen rows a frame), and that measurably changed AAEC's
/// settling (docs/design/hil.md, "Sensor"). With two, a repeat needs both offsets to
/// collide (about 1e-4).
const NOISE_LEN: usize = 1 << 18;

/// xorshift64*: fast, seeded, good enough to pick Gaussian table entries.
#[derive(Debug, Clone)]
pub(crate) struct XorShift64Star(u64);

impl XorShift64Star {
    pub(crate) fn new(seed: u64) -> Self {
        // The state must not be zero.
        Self((seed ^ 0x2545_F491_4F6C_DD1D) | 1)
    }

    #[inline(always)]
    pub(crate) fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
}

/// Precomputed noise and response tables, built once per camera.
#[derive(Debug, Clone)]
pub(crate) struct SensorTables {
    /// Halves of standard normal samples (`g / 2`), normalized to exact mean 0 and
    /// variance 1/4.
    pub(crate) half_gauss: Vec<f32>,
    /// Two fields of normal samples whose sum is half a standard normal sample in units
    /// of `kernels::NOISE_SCALE` (each has variance 1/8), at least two rows long.
    pub(crate) noise_fields: [Vec<i16>; 2],
    /// Grey level for `s = i * s_step` (see the module doc), rounded.
    pub(crate) response_lut: Box<[u8; RESPONSE_LUT_LEN]>,
    /// Table index per unit of `s`.
    pub(crate) lut_per_s: f32,
    /// Read noise variance, electrons^2.
    pub(crate) read_var_e2: f32,
    pub(crate) noise: bool,
    /// For a linear response, the grey level computed from `s` instead of read from the
    /// table (see [`Linear`]).
    pub(crate) linear: Option<Linear>,
}

/// A linear camera response without the table: `level = round(min(255, k * min(fw,
/// max(0, s^2 - sigma_r^2))))` with `s = max(0, s)`. Exact at every `s`, where the table
/// rounds `s` to one of its entries first (up to 0.06 levels near the top); and no table
/// read (eight scalar reads per eight pixels in the packed builds).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Linear {
    /// Grey levels per electron (255 x gain / full well).
    pub(crate) per_e: f32,
    /// Full well, electrons (the clip before the gain).
    pub(crate) full_well_e: f32,
}

impl Linear {
    /// Grey level at `s` (the square-root-domain signal, noise included) for read
    /// noise variance `read_var`: the sensor loops' formula.
    #[inline(always)]
    pub(crate) fn level(&self, s: f32, read_var: f32) -> u8 {
        super::kernels::linear_level(self, s, read_var)
    }
}

impl SensorTables {
    pub(crate) fn new(seed: u64, model: &super::CameraModel, response: &Response) -> Self {
        let mut rng = super::super::scene::SplitMix64::new(seed ^ 0x6A55_0000_0000_0003);
        let (gauss, mean, sd) = normal_samples(&mut rng, 1 << GAUSS_LOG2);
        let half_gauss = gauss
            .iter()
            .map(|g| (0.5 * (g - mean) / sd) as f32)
            .collect();
        let len = NOISE_LEN.max(2 * model.width as usize);
        let noise_fields = [noise_field(&mut rng, len), noise_field(&mut rng, len)];

        let s = &model.sensor;
        let gain = 10f64.powf(model.gain_db / 20.0);
        let read_var = s.read_noise_e * s.read_noise_e;
        // Electrons that reach the converter's full scale (the full well at 0 dB).
        let full_scale_e = s.full_well_e / gain;
        let s_max = (full_scale_e + read_var).sqrt() + 1.0;
        let s_step = s_max / (RESPONSE_LUT_LEN - 1) as f64;
        let mut response_lut = Box::new([0u8; RESPONSE_LUT_LEN]);
        for (i, level) in response_lut.iter_mut().enumerate() {
            let sv = i as f64 * s_step;
            // Full-well clip, then gain and the converter's full scale.
            let e = (sv * sv - read_var).clamp(0.0, s.full_well_e);
            let x = e * gain / s.full_well_e;
            *level = response.grey(x).round().clamp(0.0, 255.0) as u8;
        }
        let linear = match model.response {
            ResponseModel::Linear => true,
            ResponseModel::Gamma { gamma } => gamma == 1.0,
            ResponseModel::Table { .. } | ResponseModel::Polynomial { .. } => false,
        };
        Self {
            half_gauss,
            noise_fields,
            response_lut,
            lut_per_s: (1.0 / s_step) as f32,
            read_var_e2: read_var as f32,
            noise: s.noise,
            linear: linear.then(|| Linear {
                per_e: (255.0 * gain / s.full_well_e) as f32,
                full_well_e: s.full_well_e as f32,
            }),
        }
    }

    #[inline(always)]
    pub(crate) fn gauss_mask(&self) -> usize {
        self.half_gauss.len() - 1
    }

    /// Grey level of a pixel whose mean signal is `mean_e` electrons; `half_g` is half
    /// a standard normal sample (ignored when noise is off).
    #[inline(always)]
    pub(crate) fn grey(&self, mean_e: f32, half_g: f32) -> u8 {
        let g = if self.noise { half_g } else { 0.0 };
        let s = (mean_e.max(0.0) + self.read_var_e2).sqrt() + g;
        if let Some(l) = &self.linear {
            return l.level(s, self.read_var_e2);
        }
        let idx = (s * self.lut_per_s + 0.5).clamp(0.0, (RESPONSE_LUT_LEN - 1) as f32) as usize;
        self.response_lut[idx]
    }
}

/// `n` normal samples (Box-Muller, normalized to mean 0 and variance 1/8: two of them add
/// up to half a standard normal sample) in units of `NOISE_SCALE`.
fn noise_field(rng: &mut super::super::scene::SplitMix64, n: usize) -> Vec<i16> {
    let (g, mean, sd) = normal_samples(rng, n);
    let k = 0.5 * std::f64::consts::FRAC_1_SQRT_2 / sd / super::kernels::NOISE_SCALE as f64;
    g.iter()
        .map(|v| ((v - mean) * k).round().clamp(-32767.0, 32767.0) as i16)
        .collect()
}

/// `n` standard normal samples (Box-Muller) with their sample mean and standard
/// deviation, so callers can normalize them exactly.
fn normal_samples(rng: &mut super::super::scene::SplitMix64, n: usize) -> (Vec<f64>, f64, f64) {
    let mut g = Vec::with_capacity(n + 1);
    while g.len() < n {
        let u1 = rng.next_f64().max(1e-300);
        let u2 = rng.next_f64();
        let r = (-2.0 * u1.ln()).sqrt();
        let a = std::f64::consts::TAU * u2;
        g.push(r * a.cos());
        g.push(r * a.sin());
    }
    g.truncate(n);
    let mean = g.iter().sum::<f64>() / n as f64;
    let var = g.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
    (g, mean, var.sqrt().max(1e-12))
}

/// Electrons per unit of exitance (W/m2) during an exposure of `exposure_us`.
pub(crate) fn electrons_per_unit(model: &super::CameraModel, exposure_us: f64) -> f64 {
    model.sensor.electrons_per_w_m2_us * exposure_us
}

#[cfg(test)]
mod tests {
    use super::*;
    use markhold_exposure::ResponseModel;

    fn tables(noise: bool) -> SensorTables {
        let mut m = crate::camera::CameraModel::blackfly_s(ResponseModel::Linear);
        m.sensor.noise = noise;
        SensorTables::new(1, &m, &Response::linear())
    }

    #[test]
    fn noise_free_levels_follow_the_signal() {
        let t = tables(false);
        // Linear response: 255 at the full well (10 500 e).
        for e in [0.0f32, 100.0, 2000.0, 5250.0, 10_000.0] {
            let want = 255.0 * e / 10_500.0;
            let got = t.grey(e, 1.0) as f32;
            assert!((got - want).abs() <= 0.6, "{e} e: {got} vs {want}");
        }
        assert_eq!(t.grey(20_000.0, 0.0), 255);
        assert_eq!(t.grey(-5.0, 0.0), 0);
    }

    /// The computed linear response is the table's, without the table's rounding of `s`
    /// to one of its entries: never more than a level apart, mostly equal.
    #[test]
    fn computed_linear_levels_match_the_table() {
        for gain_db in [0.0, 12.0] {
            let mut m = crate::camera::CameraModel::blackfly_s(ResponseModel::Linear);
            m.gain_db = gain_db;
            let t = SensorTables::new(1, &m, &Response::linear());
            let l = t.linear.expect("a linear response is computed");
            let top = (RESPONSE_LUT_LEN - 1) as f32 / t.lut_per_s;
            let (mut same, n) = (0, 100_000);
            for k in 0..n {
                let s = top * 1.05 * k as f32 / n as f32;
                let idx = ((s * t.lut_per_s).round() as usize).min(RESPONSE_LUT_LEN - 1);
                let (got, table) = (l.level(s, t.read_var_e2), t.response_lut[idx]);
                assert!(
                    got.abs_diff(table) <= 1,
                    "{gain_db} dB, s {s}: {got} vs {table}"
                );
                same += (got == table) as usize;
            }
            assert!(same > n * 9 / 10, "{gain_db} dB: only {same} of {n} equal");
        }
        // Other responses keep the table.
        let m = crate::camera::CameraModel::blackfly_s(ResponseModel::Gamma { gamma: 2.2 });
        let gamma = Response::gamma(2.2).expect("a valid gamma");
        assert!(SensorTables::new(1, &m, &gamma).linear.is_none());
    }

    #[test]
    fn noise_has_the_shot_plus_read_variance() {
        let t = tables(true);
        let mut rng = XorShift64Star::new(3);
        // 4000 e: shot sd 63 e = 1.53 grey levels (linear, 255 per 10 500 e).
        let n = 200_000;
        let (mut sum, mut sum2) = (0.0f64, 0.0f64);
        for _ in 0..n {
            let g = t.half_gauss[(rng.next_u64() >> 40) as usize & t.gauss_mask()];
            let v = t.grey(4000.0, g) as f64;
            sum += v;
            sum2 += v * v;
        }
        let mean = sum / n as f64;
        let sd = (sum2 / n as f64 - mean * mean).sqrt();
        let want_sd = (4000.0f64 + 2.3 * 2.3).sqrt() * 255.0 / 10_500.0;
        assert!((mean - 4000.0 * 255.0 / 10_500.0).abs() < 0.1, "{mean}");
        // Quantization to integer levels adds 1/12 level^2.
        let want = (want_sd * want_sd + 1.0 / 12.0).sqrt();
        assert!((sd - want).abs() < 0.05 * want, "sd {sd} vs {want}");
    }
}
