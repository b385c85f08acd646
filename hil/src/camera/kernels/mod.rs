//! The per-pixel loops of the fast renderer, in builds that give bit-identical results:
//! portable (scalar, what a CPU without AVX2 runs), AVX2 (eight pixels a step) and, where
//! the CPU has AVX-512 (with VBMI), sixteen pixels a step for the rock, plate and linear
//! sensor loops (the AVX2 ones elsewhere).
//!
//! Each formula and each loop is written once here, generic over [`Lanes`]: the
//! operations a build's registers offer. `portable.rs`, `avx2.rs` and `avx512.rs`
//! implement them (one f32, eight, sixteen) and add what differs by build: how texels,
//! marker cells and response-table entries are read, how levels are narrowed to bytes.
//! So every build evaluates the same f32 operations in the same order (no FMA: Rust
//! never contracts a multiply and an add on its own), and a frame does not depend on the
//! CPU it was rendered on; `tests.rs` and `tests/camera_fast.rs` check it.

/// Wraps intrinsics as a build's token methods (see [`Lanes`]): safe, because a token
/// exists only where the CPU has the build's features.
#[cfg(target_arch = "x86_64")]
macro_rules! lane_ops {
    ($($name:ident($($a:ident: $t:ty),*) -> $r:ty = $e:expr;)*) => {$(
        #[inline(always)]
        fn $name(self, $($a: $t),*) -> $r {
            // SAFETY: the token exists only where the CPU has the build's features.
            unsafe { $e }
        }
    )*};
}

/// The same for operations that need no CPU feature (the portable build).
macro_rules! lane_fns {
    ($($name:ident($($a:ident: $t:ty),*) -> $r:ty = $e:expr;)*) => {$(
        #[inline(always)]
        fn $name(self, $($a: $t),*) -> $r {
            $e
        }
    )*};
}

/// Runs the body on the parts `o` of a run of pixels `$out` from offset `$first`
/// (counted from the run's first node) that fall in one 16-pixel span each (`t0`: the
/// part's first pixel in its span, `span`: its nodes): a part span, whole spans (their
/// nodes from windows of the node arrays: no index or division per span), a part span.
/// A macro, not a function taking a closure: a closure does not inherit AVX2 from the
/// function it is written in, and the loop bodies must (docs/design/hil.md).
macro_rules! for_span_parts {
    ($out:expr, $first:expr, $nodes:expr, |$o:ident, $t0:ident, $sp:ident| $body:expr) => {{
        let (out, first, nodes): (&mut [f32], usize, &RockNodes) = ($out, $first, $nodes);
        let (len, spans) = (out.len(), nodes.cells.len().saturating_sub(1));
        let (mut s, t0) = (first / 16, first % 16);
        let mut done = 0;
        if t0 != 0 && s < spans {
            done = (16 - t0).min(len);
            let ($o, $t0, $sp) = (&mut out[..done], t0, nodes.span(s));
            $body;
            s += 1;
        }
        let whole = ((len - done) / 16).min(spans.saturating_sub(s));
        if whole > 0 {
            let parts = out[done..done + 16 * whole].chunks_exact_mut(16);
            for ($o, $sp) in parts.zip(nodes.spans_from(s)) {
                let $t0 = 0usize;
                $body;
            }
            (done, s) = (done + 16 * whole, s + whole);
        }
        if done < len && s < spans {
            let n = (len - done).min(16);
            let ($o, $t0, $sp) = (&mut out[done..done + n], 0usize, nodes.span(s));
            $body;
        }
    }};
}

#[cfg(target_arch = "x86_64")]
mod avx2;
#[cfg(target_arch = "x86_64")]
mod avx512;
mod portable;
#[cfg(test)]
mod tests;

use super::sensor::RESPONSE_LUT_LEN;
use crate::scene::{LitTexture, Texture};
use portable::Scalar;

/// Scale of the stored noise fields: `(a + b) as f32 * NOISE_SCALE`, the sum of one
/// sample of each, is half a standard normal sample (a power of two, so the conversion
/// is exact in both builds).
pub(crate) const NOISE_SCALE: f32 = 1.0 / 4096.0;
/// Adding this to a float in [0, 2^23) leaves the nearest integer in its mantissa bits.
const ROUND_MAGIC: f32 = 8_388_608.0;

/// Whether the packed loops may read `t` by masked index without a bounds check.
fn complete(t: &Texture) -> bool {
    square(t.log2, t.data.len())
}

/// The same for a rock-and-caustic texture.
fn complete_lit(t: &LitTexture) -> bool {
    square(t.log2, t.data.len())
}

/// `len` texels make a square of side `1 << log2` whose indices fit the packed lanes.
fn square(log2: u32, len: usize) -> bool {
    log2 <= 15 && len == 1usize << (2 * log2)
}

/// A 16.16 fixed-point texel coordinate along a run: `at + step * t` (wrapping).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Walk {
    pub(crate) at: i32,
    pub(crate) step: i32,
}

impl Walk {
    /// The same walk counted from pixel `t`.
    #[inline(always)]
    pub(super) fn from(self, t: i32) -> Self {
        Self {
            at: self.at.wrapping_add(self.step.wrapping_mul(t)),
            step: self.step,
        }
    }
}

/// A quantity linear along a run: `at + step * t`.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Ramp {
    pub(crate) at: f32,
    pub(crate) step: f32,
}

impl Ramp {
    #[inline(always)]
    pub(crate) fn get(&self, t: f32) -> f32 {
        self.at + self.step * t
    }
}

/// Rock without caustics: `byte * scaled_light + offset_light` (the rock's albedo scale
/// and offset folded into the light terms by the caller).
pub(crate) struct RockRun<'a> {
    pub(crate) tex: &'a Texture,
    pub(crate) u: Walk,
    pub(crate) v: Walk,
    pub(crate) light: Ramp,
    pub(crate) add: Ramp,
}

/// Rock under caustics: `albedo * (light + caustic * byte) + add`, the ambient light's
/// caustic factor `1 + strength * (offset + scale * byte - 1)` folded into the light
/// terms (`fold_rock_cell`); albedo and caustic byte from one texel of the frame's
/// rock-and-caustic texture.
pub(crate) struct CausticRockRun<'a> {
    pub(crate) tex: &'a LitTexture,
    pub(crate) u: Walk,
    pub(crate) v: Walk,
    pub(crate) light: Ramp,
    pub(crate) caustic: Ramp,
    pub(crate) add: Ramp,
}

/// The light fields of a rock plane at the nodes of a run of spans (ambient, lamp,
/// additive; see `fast.rs`), and its texel walks at the same nodes (16.16, wrapping):
/// the rock texture's u, v (the caustic webs lie on the same grid).
pub(crate) struct RockNodes<'a> {
    /// Per node: the fields on the grid row above and their change to the one below
    /// (folded by `fold_rock_cell`).
    pub(crate) cells: &'a [[f32; 6]],
    /// The row's vertical weight between those grid rows.
    pub(crate) fy: f32,
    pub(crate) walks: [&'a [i32]; 2],
}

/// How a rock plane's light fields fold into the per-pixel formula for this frame.
#[derive(Debug, Clone, Copy)]
pub(crate) enum RockFold {
    /// Without caustics: the rock texture's `value = offset + scale * byte`.
    Plain { scale: f32, offset: f32 },
    /// Under caustics: the ambient light's factor `1 + strength * (offset + scale *
    /// byte - 1)` written `c0 + q * byte`.
    Caustic { c0: f32, q: f32 },
}

impl RockFold {
    /// Under caustics of `strength` whose bytes read `offset + scale * byte`.
    pub(crate) fn caustic(strength: f32, offset: f32, scale: f32) -> Self {
        RockFold::Caustic {
            c0: 1.0 + strength * (offset - 1.0),
            q: strength * scale,
        }
    }

    /// The three fields a rock loop takes from (ambient, lamp, additive) at a point.
    #[inline(always)]
    fn fields(self, a: f32, l: f32, d: f32) -> [f32; 3] {
        match self {
            // Daylight and lamps add up before the albedo, and the albedo's scale and
            // offset fold into the light terms (one multiply-add a pixel).
            RockFold::Plain { scale, offset } => {
                let light = a + l;
                [light * scale, d + light * offset, 0.0]
            }
            // Light without the caustic byte, its factor on the byte, additive.
            RockFold::Caustic { c0, q } => [a * c0 + l, a * q, d],
        }
    }
}

/// A rock plane's cell fields (ambient, lamp, additive; then their change down the
/// cell) as the rock loops take them (`RockFold::fields` at the top and the bottom of
/// the cell, then their change): once a cell row, not once a span.
#[inline(always)]
pub(crate) fn fold_rock_cell(c: &[f32; 6], fold: RockFold) -> [f32; 6] {
    let top = fold.fields(c[0], c[1], c[2]);
    let bottom = fold.fields(c[0] + c[3], c[1] + c[4], c[2] + c[5]);
    top_and_change(top, bottom)
}

/// A cell's fields as the loops take them: the top node's three, then the bottom
/// node's minus the top's.
#[inline(always)]
pub(crate) fn top_and_change(top: [f32; 3], bottom: [f32; 3]) -> [f32; 6] {
    [
        top[0],
        top[1],
        top[2],
        bottom[0] - top[0],
        bottom[1] - top[1],
        bottom[2] - top[2],
    ]
}

/// One span of a rock run at the nodes: both ends' cell fields and texel walks.
#[derive(Clone, Copy)]
struct SpanNodes<'a> {
    cells: &'a [[f32; 6]],
    walks: [&'a [i32]; 2],
    fy: f32,
}

impl SpanNodes<'_> {
    /// Walk `w` along the span (16 pixels: an arithmetic shift divides the delta).
    #[inline(always)]
    fn walk(&self, w: usize) -> Walk {
        let (a, b) = (self.walks[w][0], self.walks[w][1]);
        Walk {
            at: a,
            step: b.wrapping_sub(a) >> 4,
        }
    }

    /// Field `c` along the span.
    #[inline(always)]
    fn ramp(&self, c: usize) -> Ramp {
        let (l, r) = (&self.cells[0], &self.cells[1]);
        let (a, b) = (l[c] + l[c + 3] * self.fy, r[c] + r[c + 3] * self.fy);
        Ramp {
            at: a,
            step: (b - a) * (1.0 / 16.0),
        }
    }

    /// Without caustics: the cells hold the light and the additive term with the rock
    /// texture's scale and offset folded in (see `fold_rock_cell`).
    #[inline(always)]
    fn rock_run<'t>(&self, tex: &'t Texture) -> RockRun<'t> {
        RockRun {
            tex,
            u: self.walk(0),
            v: self.walk(1),
            light: self.ramp(0),
            add: self.ramp(1),
        }
    }

    /// Under caustics (the cells folded with `RockFold::Caustic`).
    #[inline(always)]
    fn caustic_run<'t>(&self, tex: &'t LitTexture) -> CausticRockRun<'t> {
        CausticRockRun {
            tex,
            u: self.walk(0),
            v: self.walk(1),
            light: self.ramp(0),
            caustic: self.ramp(1),
            add: self.ramp(2),
        }
    }
}

impl RockNodes<'_> {
    /// Span `s` (nodes `s` and `s + 1`).
    #[inline(always)]
    fn span(&self, s: usize) -> SpanNodes<'_> {
        SpanNodes {
            cells: &self.cells[s..s + 2],
            walks: [&self.walks[0][s..s + 2], &self.walks[1][s..s + 2]],
            fy: self.fy,
        }
    }

    /// Spans `s..`, in order (windows of the node arrays: no index per span).
    #[inline(always)]
    fn spans_from(&self, s: usize) -> impl Iterator<Item = SpanNodes<'_>> {
        let [wu, wv] = self.walks;
        let fy = self.fy;
        self.cells[s..]
            .windows(2)
            .zip(wu[s..].windows(2).zip(wv[s..].windows(2)))
            .map(move |(cells, (u, v))| SpanNodes {
                cells,
                walks: [u, v],
                fy,
            })
    }
}

/// The sensor's constants for one frame (see `sensor.rs`).
#[derive(Clone, Copy)]
pub(crate) struct SensorRow<'a> {
    pub(crate) read_var: f32,
    pub(crate) per_s: f32,
    pub(crate) top: f32,
    pub(crate) lut: &'a [u8; RESPONSE_LUT_LEN],
    /// A linear response computed instead of read from `lut`.
    pub(crate) linear: Option<super::sensor::Linear>,
}

/// Which build the loops run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Isa {
    Portable,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    /// The AVX2 loops, and the rock, plate and linear sensor loops sixteen pixels a step
    /// (the rock's texels picked from two-row windows).
    #[cfg(target_arch = "x86_64")]
    Avx512,
}

impl Isa {
    /// The best build this CPU runs, unless `portable` forces the scalar one.
    pub(crate) fn detect(portable: bool) -> Self {
        Self::best_up_to(if portable {
            Isa::Portable
        } else {
            Self::widest()
        })
    }

    #[cfg(target_arch = "x86_64")]
    fn widest() -> Self {
        Isa::Avx512
    }

    #[cfg(not(target_arch = "x86_64"))]
    fn widest() -> Self {
        Isa::Portable
    }

    /// The widest build this CPU runs that is not wider than `want`.
    pub(crate) fn best_up_to(want: Isa) -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            if want == Isa::Avx512 && avx512::Avx512::available() {
                return Isa::Avx512;
            }
            if want != Isa::Portable && avx2::Avx2::available() {
                return Isa::Avx2;
            }
        }
        let _ = want;
        Isa::Portable
    }

    /// Whether the AVX2 loops may run (the AVX-512 build runs them too).
    #[inline(always)]
    pub(crate) fn avx2(self) -> bool {
        self != Isa::Portable
    }
}

/// The lanes of one build: the operations the shared loops are written in. A value of an
/// implementing type is a token: it exists only where the CPU runs the build (made by
/// the build's `unsafe fn new`), so the operations are safe to call. Float operations
/// follow the packed instructions: `max(a, b)` and `min(a, b)` give `b` where either
/// is NaN.
pub(super) trait Lanes: Copy {
    /// Pixels a step.
    const N: usize;
    /// Whether the linear sensor loop narrows two steps of levels at once.
    const PAIRED_LEVELS: bool;
    /// The next narrower build: it finishes what is left of a run.
    type Half: Lanes;
    type F: Copy;
    type I: Copy;
    /// The marker's cell table as this build reads it (prepared once a run).
    type Cells: Copy;

    fn half(self) -> Self::Half;

    fn splat(self, x: f32) -> Self::F;
    fn splat_i(self, x: i32) -> Self::I;
    /// `t0, t0 + 1, ..` (pixel offsets of one step).
    fn lanes(self, t0: i32) -> Self::I;
    fn to_f(self, x: Self::I) -> Self::F;
    fn add(self, a: Self::F, b: Self::F) -> Self::F;
    fn sub(self, a: Self::F, b: Self::F) -> Self::F;
    fn mul(self, a: Self::F, b: Self::F) -> Self::F;
    fn div(self, a: Self::F, b: Self::F) -> Self::F;
    fn max(self, a: Self::F, b: Self::F) -> Self::F;
    fn min(self, a: Self::F, b: Self::F) -> Self::F;
    fn sqrt(self, a: Self::F) -> Self::F;
    /// Wrapping.
    fn add_i(self, a: Self::I, b: Self::I) -> Self::I;
    /// Wrapping, the low 32 bits.
    fn mul_i(self, a: Self::I, b: Self::I) -> Self::I;
    fn and_i(self, a: Self::I, b: Self::I) -> Self::I;
    fn shl16_i(self, a: Self::I) -> Self::I;
    /// The float's bits.
    fn bits(self, a: Self::F) -> Self::I;
    /// floor() as an integer (exact below 2^31 in magnitude).
    fn floor(self, x: Self::F) -> Self::I;

    /// `N` floats from `p`.
    ///
    /// # Safety
    /// `p..p + N` must be readable.
    unsafe fn load(self, p: *const f32) -> Self::F;
    /// `N` i16 from `p`, widened.
    ///
    /// # Safety
    /// `p..p + N` must be readable.
    unsafe fn load_i16(self, p: *const i16) -> Self::I;
    /// # Safety
    /// `p..p + N` must be writable.
    unsafe fn store(self, p: *mut f32, v: Self::F);
    /// Levels (0..=255 in each lane) as bytes.
    ///
    /// # Safety
    /// `p..p + N` must be writable.
    unsafe fn store_levels(self, p: *mut u8, v: Self::I);
    /// Two steps of levels as bytes (`PAIRED_LEVELS` builds).
    ///
    /// # Safety
    /// `p..p + 2 N` must be writable.
    unsafe fn store_level_pair(self, p: *mut u8, a: Self::I, b: Self::I);
    /// The response table's entries at `ix` (each below `lut.len()`) as bytes.
    ///
    /// # Safety
    /// `p..p + N` must be writable.
    unsafe fn store_lut(self, p: *mut u8, lut: &[u8; RESPONSE_LUT_LEN], ix: Self::I);

    /// Texel bytes at 16.16 coordinates (wrapping) as floats; packed builds need
    /// `complete(tex)`.
    fn fetch(self, tex: &Texture, u: Self::I, v: Self::I) -> Self::F;
    /// Rock and caustic bytes of the rock-and-caustic texture at 16.16 coordinates
    /// (wrapping) as floats; packed builds need `complete_lit(tex)`.
    fn fetch_lit(self, tex: &LitTexture, u: Self::I, v: Self::I) -> (Self::F, Self::F);
    /// The texels of one step of a rock run (`t`: its pixel offsets, from `t0`).
    #[inline(always)]
    fn texels(self, tex: &Texture, u: Walk, v: Walk, t0: i32, t: Self::I) -> Self::F {
        let _ = t0;
        self.fetch(tex, self.walk(u, t), self.walk(v, t))
    }
    /// `texels` of the rock-and-caustic texture.
    #[inline(always)]
    fn texels_lit(
        self,
        tex: &LitTexture,
        u: Walk,
        v: Walk,
        t0: i32,
        t: Self::I,
    ) -> (Self::F, Self::F) {
        let _ = t0;
        self.fetch_lit(tex, self.walk(u, t), self.walk(v, t))
    }

    /// The cell table for a plate run, or None where this build cannot read it (the
    /// narrower build runs it).
    fn plate_cells(self, r: &PlateRun) -> Option<Self::Cells>;
    /// Albedos of cells (iu - 1, iv - 1), (iu - 1, iv), (iu, iv - 1), (iu, iv), clamped
    /// as `PlateRun::cell` clamps them.
    fn cells4(self, r: &PlateRun, c: Self::Cells, iu: Self::I, iv: Self::I) -> [Self::F; 4];

    /// A walk at pixel offsets `t`.
    #[inline(always)]
    fn walk(self, w: Walk, t: Self::I) -> Self::I {
        self.add_i(self.splat_i(w.at), self.mul_i(self.splat_i(w.step), t))
    }

    /// A ramp at pixel offsets `t`.
    #[inline(always)]
    fn ramp(self, r: Ramp, t: Self::F) -> Self::F {
        self.add(self.splat(r.at), self.mul(self.splat(r.step), t))
    }
}

/// Rock without caustics at pixel offsets `t0..`: `byte * light + add`.
#[inline(always)]
fn rock_px<L: Lanes>(l: L, r: &RockRun, t0: i32) -> L::F {
    let t = l.lanes(t0);
    let tf = l.to_f(t);
    let b = l.texels(r.tex, r.u, r.v, t0, t);
    l.add(l.mul(b, l.ramp(r.light, tf)), l.ramp(r.add, tf))
}

/// Rock under caustics at pixel offsets `t0..`: `albedo * (light + caustic * byte) + add`.
#[inline(always)]
fn caustic_rock_px<L: Lanes>(l: L, r: &CausticRockRun, t0: i32) -> L::F {
    let t = l.lanes(t0);
    let tf = l.to_f(t);
    let (rb, cb) = l.texels_lit(r.tex, r.u, r.v, t0, t);
    let albedo = l.add(
        l.splat(r.tex.rock_offset),
        l.mul(l.splat(r.tex.rock_scale), rb),
    );
    let light = l.add(l.ramp(r.light, tf), l.mul(l.ramp(r.caustic, tf), cb));
    l.add(l.mul(albedo, light), l.ramp(r.add, tf))
}

/// A part of one 16-pixel span of a rock run (`first`: its first pixel in the span),
/// `N` pixels a step, the rest by the narrower build.
#[inline(always)]
fn rock_span<L: Lanes>(l: L, out: &mut [f32], first: usize, r: &RockRun) {
    let n = out.len();
    let mut t0 = 0usize;
    while t0 + L::N <= n {
        let m = rock_px(l, r, (first + t0) as i32);
        // SAFETY: t0 + N <= n.
        unsafe { l.store(out.as_mut_ptr().add(t0), m) };
        t0 += L::N;
    }
    if L::N > 1 && t0 < n {
        rock_span(l.half(), &mut out[t0..], first + t0, r);
    }
}

/// `rock_span` under caustics.
#[inline(always)]
fn caustic_rock_span<L: Lanes>(l: L, out: &mut [f32], first: usize, r: &CausticRockRun) {
    let n = out.len();
    let mut t0 = 0usize;
    while t0 + L::N <= n {
        let m = caustic_rock_px(l, r, (first + t0) as i32);
        // SAFETY: t0 + N <= n.
        unsafe { l.store(out.as_mut_ptr().add(t0), m) };
        t0 += L::N;
    }
    if L::N > 1 && t0 < n {
        caustic_rock_span(l.half(), &mut out[t0..], first + t0, r);
    }
}

/// Rock over a run of spans in build `l` (see `rock_nodes_run`). One loop per texture
/// kind, not a branch per span.
#[inline(always)]
fn rock_nodes<L: Lanes>(
    l: L,
    out: &mut [f32],
    first: usize,
    nodes: &RockNodes,
    rock: &Texture,
    caustic: Option<&LitTexture>,
) {
    match caustic {
        None => for_span_parts!(out, first, nodes, |o, t0, span| {
            rock_span(l, o, t0, &span.rock_run(rock))
        }),
        Some(c) => for_span_parts!(out, first, nodes, |o, t0, span| {
            caustic_rock_span(l, o, t0, &span.caustic_run(c))
        }),
    }
}

/// Rock over a run of 16-pixel spans: `out` holds the run's pixels from offset `first`
/// (counted from the run's first node) on; the last span may be short. `caustic` is the
/// frame's rock-and-caustic texture when caustics are on.
#[inline(always)]
pub(crate) fn rock_nodes_run(
    isa: Isa,
    out: &mut [f32],
    first: usize,
    nodes: &RockNodes,
    rock: &Texture,
    caustic: Option<&LitTexture>,
) {
    let readable = complete(rock) && caustic.is_none_or(complete_lit);
    match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: Avx512 is only chosen when the CPU has it (and AVX2); indices are masked
        // into the complete textures.
        Isa::Avx512 if readable => unsafe {
            avx512::rock_nodes_run(out, first, nodes, rock, caustic)
        },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        Isa::Avx2 if readable => unsafe { avx2::rock_nodes_run(out, first, nodes, rock, caustic) },
        _ => rock_nodes(Scalar, out, first, nodes, rock, caustic),
    }
}

/// The caustics on the plate for one frame (see `CausticFrame` in `fast.rs`).
#[derive(Clone, Copy)]
pub(crate) struct PlateCaustics<'a> {
    /// The frame's rock-and-caustic texture (its caustic bytes).
    pub(crate) tex: &'a LitTexture,
    pub(crate) strength: f32,
    pub(crate) texels_per_m: f32,
}

/// The front of the marker plate along one run: the cells box-filtered over the pixel
/// footprint (anti-aliased edges), caustics optional.
pub(crate) struct PlateRun<'a> {
    /// `D`, `Nu`, `Nv` of the plate along the run, from its first pixel.
    pub(crate) d: Ramp,
    pub(crate) nu: Ramp,
    pub(crate) nv: Ramp,
    pub(crate) half_marker: f32,
    pub(crate) cell_per_m: f32,
    pub(crate) inv_wu: f32,
    pub(crate) inv_wv: f32,
    /// Cell albedos with a one-cell white border, `side` = cells + 2 per row.
    pub(crate) cells: &'a [f32],
    pub(crate) side: i32,
    /// The same cells as bits, where they fit (the packed loop reads them from
    /// registers instead of gathering from `cells`).
    pub(crate) rows: Option<&'a CellRows>,
    pub(crate) caustic: Option<PlateCaustics<'a>>,
    pub(crate) ambient: Ramp,
    pub(crate) lamp: Ramp,
    pub(crate) add: Ramp,
}

/// A bordered cell table of up to 16 x 16 cells of two albedos as bits: bit `c` of
/// `bits[r]` is set where `cells[r * side + c]` is `white`. Eight 32-bit rows fit a
/// register, so the packed plate loop looks cells up with two permutes and a shift
/// instead of four gathers (docs/design/hil.md).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct CellRows {
    pub(crate) bits: [u32; 16],
    /// Two clamped rows a word, for the AVX-512 plate loop (tables up to 15 x 15):
    /// `pairs[p]` holds row `clamp(p - 1)` in its low half and row `clamp(p)` in its
    /// high half (rows clamped to the table), so pair `clamp(iv + 1, 0, side)` holds the
    /// rows of cells `iv - 1` and `iv` as `cell` clamps them.
    pub(crate) pairs: Option<[u32; 16]>,
    pub(crate) white: f32,
    pub(crate) black: f32,
}

impl CellRows {
    /// `None` when the table is larger than 16 x 16 or holds other values.
    pub(crate) fn new(cells: &[f32], side: usize, white: f32, black: f32) -> Option<Self> {
        if side > 16 || cells.len() != side * side {
            return None;
        }
        let mut bits = [0u32; 16];
        for (r, row) in cells.chunks_exact(side).enumerate() {
            for (c, &v) in row.iter().enumerate() {
                if v == white {
                    bits[r] |= 1 << c;
                } else if v != black {
                    return None;
                }
            }
        }
        let pairs = (side <= 15).then(|| {
            let row = |r: isize| bits[r.clamp(0, side as isize - 1) as usize];
            std::array::from_fn(|p| row(p as isize - 1) | row(p as isize) << 16)
        });
        Some(Self {
            bits,
            pairs,
            white,
            black,
        })
    }
}

impl PlateRun<'_> {
    /// Whether the packed loop may read `cells` at every clamped index.
    fn gather_safe(&self) -> bool {
        self.side >= 3
            && self.cells.len() >= (self.side * self.side) as usize
            && self.caustic.is_none_or(|c| complete_lit(c.tex))
    }

    /// Cell (ci, cj) of the printed grid (-1 and `cells` are the white border).
    #[inline(always)]
    fn cell(&self, ci: i32, cj: i32) -> f32 {
        let hi = self.side - 2;
        let (ci, cj) = (ci.clamp(-1, hi), cj.clamp(-1, hi));
        let i = (cj + 1) * self.side + ci + 1;
        self.cells.get(i as usize).copied().unwrap_or(0.0)
    }
}

/// Share of the pixel footprint on the lower cell: `(i - c) / w + 0.5` in [0, 1].
#[inline(always)]
fn box_weight<L: Lanes>(l: L, i: L::I, c: L::F, inv_w: L::F) -> L::F {
    let x = l.mul(l.sub(l.to_f(i), c), inv_w);
    l.min(l.max(l.add(x, l.splat(0.5)), l.splat(0.0)), l.splat(1.0))
}

/// The plate's front at pixel offsets `t0..` (see `PlateRun`).
#[inline(always)]
fn plate_px<L: Lanes>(l: L, r: &PlateRun, cells: L::Cells, t0: i32) -> L::F {
    let one = l.splat(1.0);
    let (hm, cpm) = (l.splat(r.half_marker), l.splat(r.cell_per_m));
    let t = l.to_f(l.lanes(t0));
    let inv = l.div(one, l.ramp(r.d, t));
    let u = l.mul(l.ramp(r.nu, t), inv);
    let v = l.mul(l.ramp(r.nv, t), inv);
    let cu = l.mul(l.add(u, hm), cpm);
    let cv = l.mul(l.sub(hm, v), cpm);
    let iu = l.floor(l.add(cu, l.splat(0.5)));
    let iv = l.floor(l.add(cv, l.splat(0.5)));
    let au = box_weight(l, iu, cu, l.splat(r.inv_wu));
    let av = box_weight(l, iv, cv, l.splat(r.inv_wv));
    let [c00, c01, c10, c11] = l.cells4(r, cells, iu, iv);
    let nav = l.sub(one, av);
    let left = l.add(l.mul(av, c00), l.mul(nav, c01));
    let right = l.add(l.mul(av, c10), l.mul(nav, c11));
    let albedo = l.add(l.mul(au, left), l.mul(l.sub(one, au), right));
    let c = match &r.caustic {
        Some(c) => {
            let k = l.splat(c.texels_per_m);
            let fixed = |x: L::F| l.shl16_i(l.floor(l.mul(x, k)));
            let (_, b0) = l.fetch_lit(c.tex, fixed(u), fixed(v));
            let b = l.add(
                l.splat(c.tex.caustic_offset),
                l.mul(l.splat(c.tex.caustic_scale), b0),
            );
            l.add(one, l.mul(l.splat(c.strength), l.sub(b, one)))
        }
        None => one,
    };
    let light = l.add(l.mul(l.ramp(r.ambient, t), c), l.ramp(r.lamp, t));
    l.add(l.mul(albedo, light), l.ramp(r.add, t))
}

/// The plate's front over `out` in build `l`, `N` pixels a step, the rest (or all, where
/// this build cannot read the cell table) by the narrower build.
#[inline(always)]
fn plate<L: Lanes>(l: L, out: &mut [f32], first: usize, r: &PlateRun) {
    let Some(cells) = l.plate_cells(r) else {
        return plate(l.half(), out, first, r);
    };
    let n = out.len();
    let mut t0 = 0usize;
    while t0 + L::N <= n {
        let m = plate_px(l, r, cells, (first + t0) as i32);
        // SAFETY: t0 + N <= n.
        unsafe { l.store(out.as_mut_ptr().add(t0), m) };
        t0 += L::N;
    }
    if L::N > 1 && t0 < n {
        plate(l.half(), &mut out[t0..], first + t0, r);
    }
}

/// The plate's front over `out` (pixel offsets from the ramps' origin: `first`..).
#[inline(always)]
pub(crate) fn plate_run(isa: Isa, out: &mut [f32], first: usize, r: &PlateRun) {
    match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: Avx2 (and Avx512) are only chosen when the CPU has them; indices are
        // clamped/masked.
        Isa::Avx512 if r.gather_safe() && r.rows.is_some_and(|w| w.pairs.is_some()) => unsafe {
            avx512::plate_run(out, first, r)
        },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        isa if isa.avx2() && r.gather_safe() => unsafe { avx2::plate_run(out, first, r) },
        _ => plate(Scalar, out, first, r),
    }
}

/// The sensor's constants in a build's lanes.
#[derive(Clone, Copy)]
struct SensorLanes<L: Lanes> {
    zero: L::F,
    read_var: L::F,
    noise_scale: L::F,
    per_s: L::F,
    top: L::F,
    magic: L::F,
    /// The response table's index bits.
    lut_bits: L::I,
    /// The linear response's full well, levels per electron and top level.
    full_well: L::F,
    per_e: L::F,
    top_level: L::F,
    byte: L::I,
}

impl<L: Lanes> SensorLanes<L> {
    #[inline(always)]
    fn new(l: L, s: &SensorRow) -> Self {
        let lin = s.linear.unwrap_or(super::sensor::Linear {
            per_e: 0.0,
            full_well_e: 0.0,
        });
        Self {
            zero: l.splat(0.0),
            read_var: l.splat(s.read_var),
            noise_scale: l.splat(NOISE_SCALE),
            per_s: l.splat(s.per_s),
            top: l.splat(s.top),
            magic: l.splat(ROUND_MAGIC),
            lut_bits: l.splat_i(0x7F_FFFF & (RESPONSE_LUT_LEN as i32 - 1)),
            full_well: l.splat(lin.full_well_e),
            per_e: l.splat(lin.per_e),
            top_level: l.splat(255.0),
            byte: l.splat_i(0xFF),
        }
    }

    /// The square-root-domain signal `s` of the pixels at `t0..`: mean electrons and
    /// the two noise windows in. max(m, 0): a NaN mean gives 0.
    ///
    /// # Safety
    /// `t0 + N` must not pass the end of any of the three rows.
    #[inline(always)]
    unsafe fn signal(&self, l: L, mean: &[f32], noise: [&[i16]; 2], t0: usize) -> L::F {
        let m = l.load(mean.as_ptr().add(t0));
        let ga = l.load_i16(noise[0].as_ptr().add(t0));
        let gb = l.load_i16(noise[1].as_ptr().add(t0));
        let g = l.mul(l.to_f(l.add_i(ga, gb)), self.noise_scale);
        let m0 = l.max(m, self.zero);
        l.add(l.sqrt(l.add(m0, self.read_var)), g)
    }

    /// The linear response's level at `s` (`Linear::level`), 0..=255 in each lane.
    #[inline(always)]
    fn linear_level(&self, l: L, s: L::F) -> L::I {
        let v = l.max(s, self.zero);
        let e = l.min(
            l.max(l.sub(l.mul(v, v), self.read_var), self.zero),
            self.full_well,
        );
        let y = l.min(l.mul(e, self.per_e), self.top_level);
        // The 2^23 trick rounds to the nearest integer.
        l.and_i(l.bits(l.add(y, self.magic)), self.byte)
    }

    /// The response table's index at `s`, rounded (the 2^23 trick).
    #[inline(always)]
    fn lut_index(&self, l: L, s: L::F) -> L::I {
        let x = l.min(l.max(l.mul(s, self.per_s), self.zero), self.top);
        l.and_i(l.bits(l.add(x, self.magic)), self.lut_bits)
    }
}

/// A linear response's level at `s` for read noise variance `read_var` (the portable
/// build of the sensor loop's formula).
#[inline(always)]
pub(crate) fn linear_level(lin: &super::sensor::Linear, s: f32, read_var: f32) -> u8 {
    static NO_TABLE: [u8; RESPONSE_LUT_LEN] = [0; RESPONSE_LUT_LEN];
    let row = SensorRow {
        read_var,
        per_s: 0.0,
        top: 0.0,
        lut: &NO_TABLE,
        linear: Some(*lin),
    };
    SensorLanes::new(Scalar, &row).linear_level(Scalar, s) as u8
}

/// A row through the sensor in build `l`, rows of equal length: mean electrons and the
/// two noise windows in, grey levels out.
#[inline(always)]
fn sensor<L: Lanes>(l: L, out: &mut [u8], mean: &[f32], noise: [&[i16]; 2], s: &SensorRow) {
    let k = SensorLanes::new(l, s);
    let n = out.len();
    let p = out.as_mut_ptr();
    let mut t0 = 0usize;
    if s.linear.is_some() {
        if L::PAIRED_LEVELS {
            while t0 + 2 * L::N <= n {
                // SAFETY: t0 + 2 N <= n, the length of all four rows.
                unsafe {
                    let a = k.linear_level(l, k.signal(l, mean, noise, t0));
                    let b = k.linear_level(l, k.signal(l, mean, noise, t0 + L::N));
                    l.store_level_pair(p.add(t0), a, b);
                }
                t0 += 2 * L::N;
            }
        }
        while t0 + L::N <= n {
            // SAFETY: t0 + N <= n, the length of all four rows.
            unsafe {
                let q = k.linear_level(l, k.signal(l, mean, noise, t0));
                l.store_levels(p.add(t0), q);
            }
            t0 += L::N;
        }
    } else {
        while t0 + L::N <= n {
            // SAFETY: as above.
            unsafe {
                let ix = k.lut_index(l, k.signal(l, mean, noise, t0));
                l.store_lut(p.add(t0), s.lut, ix);
            }
            t0 += L::N;
        }
    }
    if L::N > 1 && t0 < n {
        let noise = [&noise[0][t0..], &noise[1][t0..]];
        sensor(l.half(), &mut out[t0..], &mean[t0..], noise, s);
    }
}

/// `out[t] = at + step * t`.
#[inline(always)]
pub(crate) fn ramp_run(out: &mut [f32], r: Ramp) {
    for (t, m) in out.iter_mut().enumerate() {
        *m = r.get(t as f32);
    }
}

/// One row through the sensor: mean electrons and the two noise windows in, grey
/// levels out.
#[inline(always)]
pub(crate) fn sensor_run(
    isa: Isa,
    out: &mut [u8],
    mean: &[f32],
    noise: [&[i16]; 2],
    s: &SensorRow,
) {
    let n = out
        .len()
        .min(mean.len())
        .min(noise[0].len())
        .min(noise[1].len());
    let (out, mean, noise) = (&mut out[..n], &mean[..n], [&noise[0][..n], &noise[1][..n]]);
    match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: Avx512 is only chosen when the CPU has it.
        Isa::Avx512 if s.linear.is_some() => unsafe { avx512::sensor_run(out, mean, noise, s) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: Avx2 (and Avx512) are only chosen when the CPU has them.
        Isa::Avx2 | Isa::Avx512 => unsafe { avx2::sensor_run(out, mean, noise, s) },
        Isa::Portable => sensor(Scalar, out, mean, noise, s),
    }
    // A deliberate slowdown (feature `slow-render`) that the instruction gate must catch
    // (scripts/instruction-gate): about one instruction a pixel more, the picture unchanged.
    #[cfg(feature = "slow-render")]
    for b in out.iter().step_by(6) {
        std::hint::black_box(b);
    }
}
