//! The AVX2 build: eight pixels a step. Texels and response-table entries are read one
//! by one and packed (gathers were slower: docs/design/hil.md, "Tried and rejected");
//! the marker's cells come from the table held as bits in two registers.

use std::arch::x86_64::*;

use super::{
    complete, complete_lit, CellRows, Lanes, LitTexture, PlateRun, RockNodes, Scalar, SensorRow,
    Texture, RESPONSE_LUT_LEN,
};

/// The AVX2 build's lanes.
#[derive(Debug, Clone, Copy)]
pub(super) struct Avx2(());

impl Avx2 {
    /// Whether this CPU runs the build.
    pub(super) fn available() -> bool {
        std::arch::is_x86_feature_detected!("avx2")
    }

    /// # Safety
    /// The CPU must have AVX2.
    #[inline(always)]
    pub(super) unsafe fn new() -> Self {
        Self(())
    }
}

/// `CellRows` in registers: rows 0-7, rows 8-15, black, white.
type RowRegs = (__m256i, __m256i, __m256, __m256);

/// Indices of the texels at eight 16.16 coordinates in a square texture of side
/// `1 << log2` (wrapping).
#[inline(always)]
fn indices(_: Avx2, log2: u32, u: __m256i, v: __m256i) -> [u32; 8] {
    // SAFETY: the token exists only where the CPU has AVX2.
    unsafe {
        let m = _mm256_set1_epi32(((1u32 << log2) - 1) as i32);
        let tx = _mm256_and_si256(_mm256_srai_epi32::<16>(u), m);
        let ty = _mm256_and_si256(_mm256_srai_epi32::<16>(v), m);
        let idx = _mm256_or_si256(_mm256_sll_epi32(ty, _mm_cvtsi32_si128(log2 as i32)), tx);
        let mut ix = [0u32; 8];
        _mm256_storeu_si256(ix.as_mut_ptr() as *mut __m256i, idx);
        ix
    }
}

impl Lanes for Avx2 {
    const N: usize = 8;
    const PAIRED_LEVELS: bool = true;
    type Half = Scalar;
    type F = __m256;
    type I = __m256i;
    type Cells = Option<RowRegs>;

    #[inline(always)]
    fn half(self) -> Scalar {
        Scalar
    }

    lane_ops! {
        splat(x: f32) -> __m256 = _mm256_set1_ps(x);
        splat_i(x: i32) -> __m256i = _mm256_set1_epi32(x);
        lanes(t0: i32) -> __m256i =
            _mm256_add_epi32(_mm256_set1_epi32(t0), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
        to_f(x: __m256i) -> __m256 = _mm256_cvtepi32_ps(x);
        add(a: __m256, b: __m256) -> __m256 = _mm256_add_ps(a, b);
        sub(a: __m256, b: __m256) -> __m256 = _mm256_sub_ps(a, b);
        mul(a: __m256, b: __m256) -> __m256 = _mm256_mul_ps(a, b);
        div(a: __m256, b: __m256) -> __m256 = _mm256_div_ps(a, b);
        max(a: __m256, b: __m256) -> __m256 = _mm256_max_ps(a, b);
        min(a: __m256, b: __m256) -> __m256 = _mm256_min_ps(a, b);
        sqrt(a: __m256) -> __m256 = _mm256_sqrt_ps(a);
        add_i(a: __m256i, b: __m256i) -> __m256i = _mm256_add_epi32(a, b);
        mul_i(a: __m256i, b: __m256i) -> __m256i = _mm256_mullo_epi32(a, b);
        and_i(a: __m256i, b: __m256i) -> __m256i = _mm256_and_si256(a, b);
        shl16_i(a: __m256i) -> __m256i = _mm256_slli_epi32::<16>(a);
        bits(a: __m256) -> __m256i = _mm256_castps_si256(a);
        floor(x: __m256) -> __m256i = _mm256_cvttps_epi32(_mm256_floor_ps(x));
    }

    #[inline(always)]
    unsafe fn load(self, p: *const f32) -> __m256 {
        _mm256_loadu_ps(p)
    }
    #[inline(always)]
    unsafe fn load_i16(self, p: *const i16) -> __m256i {
        _mm256_cvtepi16_epi32(_mm_loadu_si128(p as *const __m128i))
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32, v: __m256) {
        _mm256_storeu_ps(p, v)
    }
    #[inline(always)]
    unsafe fn store_levels(self, p: *mut u8, q: __m256i) {
        // Eight levels (0..=255 in i32 lanes) to eight bytes.
        let p16 = _mm256_packus_epi32(q, q);
        let p8 = _mm256_packus_epi16(p16, p16);
        let b = _mm_unpacklo_epi32(
            _mm256_castsi256_si128(p8),
            _mm256_extracti128_si256::<1>(p8),
        );
        _mm_storel_epi64(p as *mut __m128i, b);
    }
    #[inline(always)]
    unsafe fn store_level_pair(self, p: *mut u8, a: __m256i, b: __m256i) {
        // Two packs and one permute put both steps' levels in order in the low 16 bytes
        // (one store, half the loop's bookkeeping).
        let order = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
        let p8 = _mm256_packus_epi16(_mm256_packus_epi32(a, b), _mm256_setzero_si256());
        let bytes = _mm256_permutevar8x32_epi32(p8, order);
        _mm_storeu_si128(p as *mut __m128i, _mm256_castsi256_si128(bytes));
    }
    #[inline(always)]
    unsafe fn store_lut(self, p: *mut u8, lut: &[u8; RESPONSE_LUT_LEN], ix: __m256i) {
        let mut idx = [0u32; 8];
        _mm256_storeu_si256(idx.as_mut_ptr() as *mut __m256i, ix);
        // Eight table reads into one 8-byte store.
        let mut word = 0u64;
        for (k, &i) in idx.iter().enumerate() {
            let level = lut[i as usize & (RESPONSE_LUT_LEN - 1)];
            word |= (level as u64) << (8 * k);
        }
        std::ptr::copy_nonoverlapping(word.to_le_bytes().as_ptr(), p, 8);
    }

    /// Eight texel bytes as floats: scalar reads packed into one word.
    #[inline(always)]
    fn fetch(self, tex: &Texture, u: __m256i, v: __m256i) -> __m256 {
        debug_assert!(complete(tex));
        let ix = indices(self, tex.log2, u, v);
        let d = tex.data.as_ptr();
        let mut word = 0u64;
        for (k, &i) in ix.iter().enumerate() {
            // SAFETY: the index is masked into the texture, which is complete (the
            // dispatch checks it).
            word |= (unsafe { *d.add(i as usize) } as u64) << (8 * k);
        }
        // SAFETY: the token exists only where the CPU has AVX2.
        unsafe { _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_cvtsi64_si128(word as i64))) }
    }

    /// Eight rock-and-caustic texels: (rock bytes, caustic bytes) as floats.
    #[inline(always)]
    fn fetch_lit(self, tex: &LitTexture, u: __m256i, v: __m256i) -> (__m256, __m256) {
        debug_assert!(complete_lit(tex));
        let ix = indices(self, tex.log2, u, v);
        let d = tex.data.as_ptr();
        let (mut lo, mut hi) = (0u64, 0u64);
        for (k, &i) in ix.iter().enumerate() {
            // SAFETY: as in `fetch`.
            let w = unsafe { *d.add(i as usize) } as u64;
            if k < 4 {
                lo |= w << (16 * k);
            } else {
                hi |= w << (16 * (k - 4));
            }
        }
        // SAFETY: the token exists only where the CPU has AVX2.
        unsafe {
            let w = _mm256_cvtepu16_epi32(_mm_set_epi64x(hi as i64, lo as i64));
            let rock = _mm256_and_si256(w, _mm256_set1_epi32(0xFF));
            let caustic = _mm256_srli_epi32::<8>(w);
            (_mm256_cvtepi32_ps(rock), _mm256_cvtepi32_ps(caustic))
        }
    }

    #[inline(always)]
    fn plate_cells(self, r: &PlateRun) -> Option<Option<RowRegs>> {
        // SAFETY: the token exists only where the CPU has AVX2.
        Some(r.rows.map(|rows| unsafe { row_regs(rows) }))
    }

    #[inline(always)]
    fn cells4(self, r: &PlateRun, c: Option<RowRegs>, iu: __m256i, iv: __m256i) -> [__m256; 4] {
        // SAFETY: the token exists only where the CPU has AVX2; the caller (the dispatch)
        // checked `r.gather_safe()`.
        unsafe {
            let ione = _mm256_set1_epi32(1);
            let (iu1, iv1) = (_mm256_sub_epi32(iu, ione), _mm256_sub_epi32(iv, ione));
            [
                cell_of(r, c, iu1, iv1),
                cell_of(r, c, iu1, iv),
                cell_of(r, c, iu, iv1),
                cell_of(r, c, iu, iv),
            ]
        }
    }
}

/// The cell albedo at (ci, cj) gathered from `r.cells` (clamped as `PlateRun::cell`).
#[inline(always)]
unsafe fn cell(r: &PlateRun, ci: __m256i, cj: __m256i) -> __m256 {
    let (lo, hi) = (_mm256_set1_epi32(-1), _mm256_set1_epi32(r.side - 2));
    let ci = _mm256_min_epi32(_mm256_max_epi32(ci, lo), hi);
    let cj = _mm256_min_epi32(_mm256_max_epi32(cj, lo), hi);
    let one = _mm256_set1_epi32(1);
    let idx = _mm256_add_epi32(
        _mm256_mullo_epi32(_mm256_add_epi32(cj, one), _mm256_set1_epi32(r.side)),
        _mm256_add_epi32(ci, one),
    );
    _mm256_i32gather_ps::<4>(r.cells.as_ptr(), idx)
}

#[inline(always)]
unsafe fn row_regs(rows: &CellRows) -> RowRegs {
    (
        _mm256_loadu_si256(rows.bits.as_ptr() as *const __m256i),
        _mm256_loadu_si256(rows.bits.as_ptr().add(8) as *const __m256i),
        _mm256_set1_ps(rows.black),
        _mm256_set1_ps(rows.white),
    )
}

/// `cell` from the bits where they are held: the same clamped cell, the same albedo.
#[inline(always)]
unsafe fn cell_of(r: &PlateRun, regs: Option<RowRegs>, ci: __m256i, cj: __m256i) -> __m256 {
    let Some((lo_rows, hi_rows, black, white)) = regs else {
        return cell(r, ci, cj);
    };
    let (lo, hi) = (_mm256_set1_epi32(-1), _mm256_set1_epi32(r.side - 2));
    let one = _mm256_set1_epi32(1);
    let c = _mm256_add_epi32(_mm256_min_epi32(_mm256_max_epi32(ci, lo), hi), one);
    let row = _mm256_add_epi32(_mm256_min_epi32(_mm256_max_epi32(cj, lo), hi), one);
    // The row's bits: from the first register for rows 0-7, the second for 8-15 (a
    // permute reads the index's low three bits).
    let bits = _mm256_blendv_epi8(
        _mm256_permutevar8x32_epi32(lo_rows, row),
        _mm256_permutevar8x32_epi32(hi_rows, row),
        _mm256_cmpgt_epi32(row, _mm256_set1_epi32(7)),
    );
    let bit = _mm256_and_si256(_mm256_srlv_epi32(bits, c), one);
    _mm256_blendv_ps(
        black,
        white,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(bit, one)),
    )
}

/// # Safety
/// The CPU must have AVX2; the textures must be complete.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn rock_nodes_run(
    out: &mut [f32],
    first: usize,
    nodes: &RockNodes,
    rock: &Texture,
    caustic: Option<&LitTexture>,
) {
    super::rock_nodes(Avx2::new(), out, first, nodes, rock, caustic)
}

/// # Safety
/// The CPU must have AVX2; `r.gather_safe()`.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn plate_run(out: &mut [f32], first: usize, r: &PlateRun) {
    super::plate(Avx2::new(), out, first, r)
}

/// # Safety
/// The CPU must have AVX2; the four rows of equal length.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn sensor_run(out: &mut [u8], mean: &[f32], noise: [&[i16]; 2], s: &SensorRow) {
    super::sensor(Avx2::new(), out, mean, noise, s)
}
