//! The sensor: electrons with shot and read noise, full-well clip, analog gain, the
//! camera response and 8-bit quantization.

use markhold_exposure::Response;

/// Entries of the response lookup table over the normalized signal [0, 1].
pub(crate) const RESPONSE_LUT_LEN: usize = 1 << 14;
/// Entries of the Gaussian table (power of two: indexed with a mask).
const GAUSS_LOG2: u32 = 16;

/// xorshift64*: fast, seeded, good enough to pick Gaussian table entries.
#[derive(Debug, Clone)]
pub(crate) struct XorShift64Star(u64);

impl XorShift64Star {
    pub(crate) fn new(seed: u64) -> Self {
        // The state must not be zero.
        Self(seed ^ 0x2545_F491_4F6C_DD1D | 1)
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
    /// Standard normal samples, normalized to exact mean 0 and variance 1.
    pub(crate) gauss: Vec<f32>,
    /// Grey level for normalized signal `i / (RESPONSE_LUT_LEN - 1)`, rounded.
    pub(crate) response_lut: Vec<u8>,
}

impl SensorTables {
    pub(crate) fn new(seed: u64, response: &Response) -> Self {
        let mut rng = super::super::scene::SplitMix64::new(seed ^ 0x6A55_0000_0000_0003);
        let n = 1usize << GAUSS_LOG2;
        let mut gauss = Vec::with_capacity(n);
        while gauss.len() < n {
            // Box-Muller.
            let u1 = rng.next_f64().max(1e-300);
            let u2 = rng.next_f64();
            let r = (-2.0 * u1.ln()).sqrt();
            let a = std::f64::consts::TAU * u2;
            gauss.push(r * a.cos());
            gauss.push(r * a.sin());
        }
        let mean = gauss.iter().sum::<f64>() / n as f64;
        let var = gauss.iter().map(|g| (g - mean).powi(2)).sum::<f64>() / n as f64;
        let sd = var.sqrt().max(1e-12);
        let gauss = gauss.iter().map(|g| ((g - mean) / sd) as f32).collect();
        let response_lut = (0..RESPONSE_LUT_LEN)
            .map(|i| {
                let x = i as f64 / (RESPONSE_LUT_LEN - 1) as f64;
                response.grey(x).round().clamp(0.0, 255.0) as u8
            })
            .collect();
        Self {
            gauss,
            response_lut,
        }
    }

    #[inline(always)]
    pub(crate) fn gauss_mask(&self) -> usize {
        self.gauss.len() - 1
    }
}

/// How one frame turns light into grey levels: the per-frame constants of the sensor.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Exposure {
    /// Electrons per unit of exitance (W/m2) during this exposure, at 0 dB.
    pub(crate) e_per_unit: f64,
    pub(crate) full_well_e: f32,
    pub(crate) read_var_e2: f32,
    /// Scale from electrons to response-table index (gain and full scale folded in).
    pub(crate) lut_per_e: f32,
    pub(crate) noise: bool,
}

impl Exposure {
    pub(crate) fn new(model: &super::CameraModel, exposure_us: f64) -> Self {
        let s = &model.sensor;
        let gain = 10f64.powf(model.gain_db / 20.0);
        Self {
            e_per_unit: s.electrons_per_w_m2_us * exposure_us,
            full_well_e: s.full_well_e as f32,
            read_var_e2: (s.read_noise_e * s.read_noise_e) as f32,
            // x = e * gain / full_well; LUT index = x * (len - 1).
            lut_per_e: (gain / s.full_well_e * (RESPONSE_LUT_LEN - 1) as f64) as f32,
            noise: s.noise,
        }
    }

    /// Grey level of a pixel whose mean signal is `mean_e` electrons; `g` is a standard
    /// normal sample.
    #[inline(always)]
    pub(crate) fn grey(&self, mean_e: f32, g: f32, lut: &[u8]) -> u8 {
        let e = if self.noise {
            // Shot noise (Poisson, Gaussian approximation) plus read noise.
            mean_e + (mean_e + self.read_var_e2).sqrt() * g
        } else {
            mean_e
        };
        // Full-well clip, then gain and full scale of the converter.
        let e = e.clamp(0.0, self.full_well_e);
        let idx = ((e * self.lut_per_e + 0.5) as usize).min(RESPONSE_LUT_LEN - 1);
        lut[idx]
    }
}
