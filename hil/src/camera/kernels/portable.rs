//! The portable build: one pixel a step in plain f32 and i32, what a CPU without AVX2
//! runs and what every packed build finishes a run with.

use super::{Lanes, PlateRun, RESPONSE_LUT_LEN};
use crate::scene::{LitTexture, Texture};

/// The portable build's lanes (any CPU runs them).
#[derive(Debug, Clone, Copy)]
pub(super) struct Scalar;

/// floor() as an integer without a libm call (baseline x86-64 has no rounding
/// instruction); exact, like the packed builds' rounding instruction.
#[inline(always)]
fn floor_i32(x: f32) -> i32 {
    let i = x as i32;
    i - ((i as f32) > x) as i32
}

impl Lanes for Scalar {
    const N: usize = 1;
    const PAIRED_LEVELS: bool = false;
    type Half = Scalar;
    type F = f32;
    type I = i32;
    type Cells = ();

    lane_fns! {
        half() -> Scalar = Scalar;
        splat(x: f32) -> f32 = x;
        splat_i(x: i32) -> i32 = x;
        lanes(t0: i32) -> i32 = t0;
        to_f(x: i32) -> f32 = x as f32;
        add(a: f32, b: f32) -> f32 = a + b;
        sub(a: f32, b: f32) -> f32 = a - b;
        mul(a: f32, b: f32) -> f32 = a * b;
        div(a: f32, b: f32) -> f32 = a / b;
        // As the packed instructions: `b` where either is NaN.
        max(a: f32, b: f32) -> f32 = if a > b { a } else { b };
        min(a: f32, b: f32) -> f32 = if a < b { a } else { b };
        sqrt(a: f32) -> f32 = a.sqrt();
        add_i(a: i32, b: i32) -> i32 = a.wrapping_add(b);
        mul_i(a: i32, b: i32) -> i32 = a.wrapping_mul(b);
        and_i(a: i32, b: i32) -> i32 = a & b;
        shl16_i(a: i32) -> i32 = a << 16;
        bits(a: f32) -> i32 = a.to_bits() as i32;
        floor(x: f32) -> i32 = floor_i32(x);
    }

    #[inline(always)]
    unsafe fn load(self, p: *const f32) -> f32 {
        *p
    }
    #[inline(always)]
    unsafe fn load_i16(self, p: *const i16) -> i32 {
        *p as i32
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32, v: f32) {
        *p = v;
    }
    #[inline(always)]
    unsafe fn store_levels(self, p: *mut u8, v: i32) {
        *p = v as u8;
    }
    #[inline(always)]
    unsafe fn store_level_pair(self, p: *mut u8, a: i32, b: i32) {
        *p = a as u8;
        *p.add(1) = b as u8;
    }
    #[inline(always)]
    unsafe fn store_lut(self, p: *mut u8, lut: &[u8; RESPONSE_LUT_LEN], ix: i32) {
        *p = lut[ix as usize & (RESPONSE_LUT_LEN - 1)];
    }

    #[inline(always)]
    fn fetch(self, tex: &Texture, u: i32, v: i32) -> f32 {
        tex.byte(u >> 16, v >> 16) as f32
    }
    #[inline(always)]
    fn fetch_lit(self, tex: &LitTexture, u: i32, v: i32) -> (f32, f32) {
        let w = tex.word(u >> 16, v >> 16);
        ((w & 0xFF) as f32, (w >> 8) as f32)
    }

    #[inline(always)]
    fn plate_cells(self, _: &PlateRun) -> Option<()> {
        Some(())
    }
    #[inline(always)]
    fn cells4(self, r: &PlateRun, _: (), iu: i32, iv: i32) -> [f32; 4] {
        [
            r.cell(iu - 1, iv - 1),
            r.cell(iu - 1, iv),
            r.cell(iu, iv - 1),
            r.cell(iu, iv),
        ]
    }
}
