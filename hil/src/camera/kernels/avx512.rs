//! The AVX-512 build (with VBMI): the rock, plate and linear sensor loops sixteen
//! pixels a step (the other loops are the AVX2 ones). The rock takes one whole span a
//! step: where a span's texels lie in two texture rows of 64 bytes (the usual case: a
//! span covers about nine texels at 1 m), both rows are loaded and one two-register
//! byte permute picks the sixteen texels; elsewhere they are read one by one. The plate
//! reads the four cells around a pixel from one permute of paired rows
//! (`CellRows::pairs`) and two shifts.

use std::arch::x86_64::*;

use super::avx2::Avx2;
use super::{
    complete, complete_lit, Lanes, LitTexture, PlateRun, RockNodes, SensorRow, Texture, Walk,
    RESPONSE_LUT_LEN,
};

/// The AVX-512 build's lanes.
#[derive(Debug, Clone, Copy)]
pub(super) struct Avx512(());

impl Avx512 {
    /// Whether this CPU runs the build (AVX2 too: the narrower loops finish runs).
    pub(super) fn available() -> bool {
        Avx2::available()
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512vl")
            && std::arch::is_x86_feature_detected!("avx512vbmi")
    }

    /// # Safety
    /// The CPU must have AVX2 and AVX-512 F, BW, VL and VBMI.
    #[inline(always)]
    pub(super) unsafe fn new() -> Self {
        Self(())
    }
}

/// Texel indices at sixteen 16.16 coordinates in a square texture of side `1 << log2`
/// (wrapping).
#[inline(always)]
fn indices(_: Avx512, log2: u32, u: __m512i, v: __m512i) -> [u32; 16] {
    // SAFETY: the token exists only where the CPU has AVX-512.
    unsafe {
        let m = _mm512_set1_epi32(((1u32 << log2) - 1) as i32);
        let tx = _mm512_and_si512(_mm512_srai_epi32::<16>(u), m);
        let ty = _mm512_and_si512(_mm512_srai_epi32::<16>(v), m);
        let idx = _mm512_or_si512(_mm512_sll_epi32(ty, _mm_cvtsi32_si128(log2 as i32)), tx);
        let mut ix = [0u32; 16];
        _mm512_storeu_si512(ix.as_mut_ptr() as *mut __m512i, idx);
        ix
    }
}

/// The lowest and highest whole texel a walk reaches over a span's 16 pixels, or None
/// where `at + step * t` leaves i32 (the lanes wrap there, so they are not monotonic).
#[inline(always)]
fn span_extent(w: Walk) -> Option<(i32, i32)> {
    let a0 = w.at as i64;
    let a15 = a0 + 15 * w.step as i64;
    if a15 < i32::MIN as i64 || a15 > i32::MAX as i64 {
        return None;
    }
    let (t0, t15) = ((a0 >> 16) as i32, (a15 >> 16) as i32);
    Some((t0.min(t15), t0.max(t15)))
}

/// Where a span's texels lie in a window of two texture rows, `width` texels wide: the
/// two rows' first texel indices, and the lane offsets that turn a lane's whole texel
/// (u, v) into its place in the window (`u - du`, `(v - vlo) * width`). None where the
/// span reaches wider, over more than two rows, or across the texture's edge in u.
#[inline(always)]
pub(super) fn span_window(
    log2: u32,
    u: Walk,
    v: Walk,
    width: i32,
) -> Option<(usize, usize, i32, i32)> {
    let (ulo, uhi) = span_extent(u)?;
    let (vlo, vhi) = span_extent(v)?;
    let n = 1i32 << log2;
    let mask = n - 1;
    let tx = ulo & mask;
    if n < width || uhi - ulo >= width || vhi - vlo > 1 || tx + (uhi - ulo) >= n {
        return None;
    }
    // The window starts at the span's first texel, or ends at the row's end.
    let start = tx.min(n - width);
    let row = |r: i32| (((r & mask) << log2) + start) as usize;
    Some((row(vlo), row(vlo + 1), ulo - (tx - start), vlo))
}

/// Sixteen texel bytes from a window of two texture rows (64 texels each): one
/// two-register byte permute instead of sixteen reads (see `span_window`). `tu`, `tv`
/// are the walks `u`, `v` at lanes 0..16.
#[inline(always)]
fn fetch_window(
    _: Avx512,
    tex: &Texture,
    u: Walk,
    v: Walk,
    tu: __m512i,
    tv: __m512i,
) -> Option<__m512> {
    let (r0, r1, du, vlo) = span_window(tex.log2, u, v, 64)?;
    let d = tex.data.as_ptr();
    // SAFETY: the token exists only where the CPU has AVX-512 (VBMI); both rows' 64
    // bytes lie in the texture, which is complete (the dispatch checks it), as
    // `span_window` places the window inside a row.
    unsafe {
        let (a, b) = (
            _mm512_loadu_si512(d.add(r0) as *const __m512i),
            _mm512_loadu_si512(d.add(r1) as *const __m512i),
        );
        let col = _mm512_sub_epi32(_mm512_srai_epi32::<16>(tu), _mm512_set1_epi32(du));
        let row = _mm512_sub_epi32(_mm512_srai_epi32::<16>(tv), _mm512_set1_epi32(vlo));
        let at = _mm512_add_epi32(col, _mm512_slli_epi32::<6>(row));
        let idx = _mm512_castsi128_si512(_mm512_cvtepi32_epi8(at));
        let bytes = _mm512_castsi512_si128(_mm512_permutex2var_epi8(a, idx, b));
        Some(_mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(bytes)))
    }
}

/// `fetch_window` of the rock-and-caustic texture: two rows of 32 texels
/// (two-register word permute).
#[inline(always)]
fn fetch_lit_window(
    _: Avx512,
    tex: &LitTexture,
    u: Walk,
    v: Walk,
    tu: __m512i,
    tv: __m512i,
) -> Option<(__m512, __m512)> {
    let (r0, r1, du, vlo) = span_window(tex.log2, u, v, 32)?;
    let d = tex.data.as_ptr();
    // SAFETY: as in `fetch_window` (32 words a row).
    unsafe {
        let (a, b) = (
            _mm512_loadu_si512(d.add(r0) as *const __m512i),
            _mm512_loadu_si512(d.add(r1) as *const __m512i),
        );
        let col = _mm512_sub_epi32(_mm512_srai_epi32::<16>(tu), _mm512_set1_epi32(du));
        let row = _mm512_sub_epi32(_mm512_srai_epi32::<16>(tv), _mm512_set1_epi32(vlo));
        let at = _mm512_add_epi32(col, _mm512_slli_epi32::<5>(row));
        let idx = _mm512_castsi256_si512(_mm512_cvtepi32_epi16(at));
        let words = _mm512_castsi512_si256(_mm512_permutex2var_epi16(a, idx, b));
        let w = _mm512_cvtepu16_epi32(words);
        let rock = _mm512_and_si512(w, _mm512_set1_epi32(0xFF));
        let caustic = _mm512_srli_epi32::<8>(w);
        Some((_mm512_cvtepi32_ps(rock), _mm512_cvtepi32_ps(caustic)))
    }
}

/// `x` clamped to `lo..=hi`.
#[inline(always)]
unsafe fn clamp(x: __m512i, lo: i32, hi: i32) -> __m512i {
    _mm512_min_epi32(
        _mm512_max_epi32(x, _mm512_set1_epi32(lo)),
        _mm512_set1_epi32(hi),
    )
}

impl Lanes for Avx512 {
    const N: usize = 16;
    const PAIRED_LEVELS: bool = false;
    type Half = Avx2;
    type F = __m512;
    type I = __m512i;
    /// The paired rows, black, white.
    type Cells = (__m512i, __m512, __m512);

    #[inline(always)]
    fn half(self) -> Avx2 {
        // SAFETY: a CPU with this build has AVX2 (`available`).
        unsafe { Avx2::new() }
    }

    lane_ops! {
        splat(x: f32) -> __m512 = _mm512_set1_ps(x);
        splat_i(x: i32) -> __m512i = _mm512_set1_epi32(x);
        lanes(t0: i32) -> __m512i = _mm512_add_epi32(
            _mm512_set1_epi32(t0),
            _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15),
        );
        to_f(x: __m512i) -> __m512 = _mm512_cvtepi32_ps(x);
        add(a: __m512, b: __m512) -> __m512 = _mm512_add_ps(a, b);
        sub(a: __m512, b: __m512) -> __m512 = _mm512_sub_ps(a, b);
        mul(a: __m512, b: __m512) -> __m512 = _mm512_mul_ps(a, b);
        div(a: __m512, b: __m512) -> __m512 = _mm512_div_ps(a, b);
        max(a: __m512, b: __m512) -> __m512 = _mm512_max_ps(a, b);
        min(a: __m512, b: __m512) -> __m512 = _mm512_min_ps(a, b);
        sqrt(a: __m512) -> __m512 = _mm512_sqrt_ps(a);
        add_i(a: __m512i, b: __m512i) -> __m512i = _mm512_add_epi32(a, b);
        mul_i(a: __m512i, b: __m512i) -> __m512i = _mm512_mullo_epi32(a, b);
        and_i(a: __m512i, b: __m512i) -> __m512i = _mm512_and_si512(a, b);
        shl16_i(a: __m512i) -> __m512i = _mm512_slli_epi32::<16>(a);
        bits(a: __m512) -> __m512i = _mm512_castps_si512(a);
        floor(x: __m512) -> __m512i = _mm512_cvttps_epi32(_mm512_roundscale_ps::<
            { _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC },
        >(x));
    }

    #[inline(always)]
    unsafe fn load(self, p: *const f32) -> __m512 {
        _mm512_loadu_ps(p)
    }
    #[inline(always)]
    unsafe fn load_i16(self, p: *const i16) -> __m512i {
        _mm512_cvtepi16_epi32(_mm256_loadu_si256(p as *const __m256i))
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32, v: __m512) {
        _mm512_storeu_ps(p, v)
    }
    #[inline(always)]
    unsafe fn store_levels(self, p: *mut u8, q: __m512i) {
        // The levels narrow to bytes in one instruction.
        _mm_storeu_si128(p as *mut __m128i, _mm512_cvtepi32_epi8(q));
    }
    #[inline(always)]
    unsafe fn store_level_pair(self, p: *mut u8, a: __m512i, b: __m512i) {
        self.store_levels(p, a);
        self.store_levels(p.add(16), b);
    }
    #[inline(always)]
    unsafe fn store_lut(self, p: *mut u8, lut: &[u8; RESPONSE_LUT_LEN], ix: __m512i) {
        let mut idx = [0u32; 16];
        _mm512_storeu_si512(idx.as_mut_ptr() as *mut __m512i, ix);
        for (k, &i) in idx.iter().enumerate() {
            *p.add(k) = lut[i as usize & (RESPONSE_LUT_LEN - 1)];
        }
    }

    /// Sixteen texel bytes as floats, read one by one.
    #[inline(always)]
    fn fetch(self, tex: &Texture, u: __m512i, v: __m512i) -> __m512 {
        debug_assert!(complete(tex));
        let ix = indices(self, tex.log2, u, v);
        let d = tex.data.as_ptr();
        let (mut lo, mut hi) = (0u64, 0u64);
        for k in 0..8 {
            // SAFETY: the indices are masked into the texture, which is complete (the
            // dispatch checks it).
            let (a, b) = unsafe { (*d.add(ix[k] as usize), *d.add(ix[k + 8] as usize)) };
            lo |= (a as u64) << (8 * k);
            hi |= (b as u64) << (8 * k);
        }
        // SAFETY: the token exists only where the CPU has AVX-512.
        unsafe { _mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(_mm_set_epi64x(hi as i64, lo as i64))) }
    }

    /// Sixteen rock-and-caustic texels: (rock bytes, caustic bytes) as floats.
    #[inline(always)]
    fn fetch_lit(self, tex: &LitTexture, u: __m512i, v: __m512i) -> (__m512, __m512) {
        debug_assert!(complete_lit(tex));
        let ix = indices(self, tex.log2, u, v);
        let d = tex.data.as_ptr();
        let mut q = [0u64; 4];
        for k in 0..4 {
            for (j, w) in q.iter_mut().enumerate() {
                // SAFETY: as in `fetch`.
                *w |= (unsafe { *d.add(ix[4 * j + k] as usize) } as u64) << (16 * k);
            }
        }
        // SAFETY: the token exists only where the CPU has AVX-512.
        unsafe {
            let lo = _mm256_set_epi64x(q[3] as i64, q[2] as i64, q[1] as i64, q[0] as i64);
            let w = _mm512_cvtepu16_epi32(lo);
            let rock = _mm512_and_si512(w, _mm512_set1_epi32(0xFF));
            let caustic = _mm512_srli_epi32::<8>(w);
            (_mm512_cvtepi32_ps(rock), _mm512_cvtepi32_ps(caustic))
        }
    }

    /// From a two-row window where the step's texels fit one, else one by one.
    #[inline(always)]
    fn texels(self, tex: &Texture, u: Walk, v: Walk, t0: i32, t: __m512i) -> __m512 {
        let (tu, tv) = (self.walk(u, t), self.walk(v, t));
        match fetch_window(self, tex, u.from(t0), v.from(t0), tu, tv) {
            Some(b) => b,
            None => self.fetch(tex, tu, tv),
        }
    }

    #[inline(always)]
    fn texels_lit(
        self,
        tex: &LitTexture,
        u: Walk,
        v: Walk,
        t0: i32,
        t: __m512i,
    ) -> (__m512, __m512) {
        let (tu, tv) = (self.walk(u, t), self.walk(v, t));
        match fetch_lit_window(self, tex, u.from(t0), v.from(t0), tu, tv) {
            Some(b) => b,
            None => self.fetch_lit(tex, tu, tv),
        }
    }

    #[inline(always)]
    fn plate_cells(self, r: &PlateRun) -> Option<Self::Cells> {
        let rows = r.rows?;
        let pairs = rows.pairs?;
        // SAFETY: the token exists only where the CPU has AVX-512.
        unsafe {
            Some((
                _mm512_loadu_si512(pairs.as_ptr() as *const __m512i),
                _mm512_set1_ps(rows.black),
                _mm512_set1_ps(rows.white),
            ))
        }
    }

    #[inline(always)]
    fn cells4(self, r: &PlateRun, c: Self::Cells, iu: __m512i, iv: __m512i) -> [__m512; 4] {
        let (pairs, black, white) = c;
        let side = r.side;
        // SAFETY: the token exists only where the CPU has AVX-512.
        unsafe {
            let (lo_bit, hi_bit) = (_mm512_set1_epi32(1), _mm512_set1_epi32(1 << 16));
            // Rows of cells iv - 1 (low half) and iv (high half), then the columns of
            // cells iu - 1 and iu as `PlateRun::cell` clamps them.
            let pair =
                _mm512_permutexvar_epi32(clamp(_mm512_add_epi32(iv, lo_bit), 0, side), pairs);
            let c0 = clamp(iu, 0, side - 1);
            let c1 = clamp(_mm512_add_epi32(iu, lo_bit), 0, side - 1);
            let (w0, w1) = (_mm512_srlv_epi32(pair, c0), _mm512_srlv_epi32(pair, c1));
            let cell = |w: __m512i, bit: __m512i| {
                _mm512_mask_blend_ps(_mm512_test_epi32_mask(w, bit), black, white)
            };
            [
                cell(w0, lo_bit),
                cell(w0, hi_bit),
                cell(w1, lo_bit),
                cell(w1, hi_bit),
            ]
        }
    }
}

/// # Safety
/// The CPU must have the build's features (`Avx512::available`); the textures must be
/// complete.
#[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl,avx512vbmi")]
pub(super) unsafe fn rock_nodes_run(
    out: &mut [f32],
    first: usize,
    nodes: &RockNodes,
    rock: &Texture,
    caustic: Option<&LitTexture>,
) {
    super::rock_nodes(Avx512::new(), out, first, nodes, rock, caustic)
}

/// # Safety
/// The CPU must have the build's features; `r.gather_safe()`.
#[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl,avx512vbmi")]
pub(super) unsafe fn plate_run(out: &mut [f32], first: usize, r: &PlateRun) {
    super::plate(Avx512::new(), out, first, r)
}

/// # Safety
/// The CPU must have the build's features; the four rows of equal length.
#[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl,avx512vbmi")]
pub(super) unsafe fn sensor_run(out: &mut [u8], mean: &[f32], noise: [&[i16]; 2], s: &SensorRow) {
    super::sensor(Avx512::new(), out, mean, noise, s)
}
