//! The per-pixel loops of the fast renderer, in builds that give bit-identical results:
//! a portable one (scalar, what a CPU without AVX2 runs), an AVX2 one (eight pixels per
//! instruction; texels and table entries still read one by one) and, where the CPU has
//! AVX-512 (with VBMI), the AVX2 one with its rock, plate and linear sensor loops sixteen
//! pixels a step (the rock's texels picked from two-row windows). All evaluate the same formula with the same f32
//! operations in the same order (no FMA: Rust never contracts a multiply and an add on
//! its own), so a frame does not depend on the CPU it was rendered on;
//! `tests/camera_fast.rs` checks it.

use crate::scene::{LitTexture, Texture};

/// Scale of the stored noise fields: `(a + b) as f32 * NOISE_SCALE`, the sum of one
/// sample of each, is half a standard normal sample (a power of two, so the conversion
/// is exact in both builds).
pub(crate) const NOISE_SCALE: f32 = 1.0 / 4096.0;
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

/// Texel byte at 16.16 fixed-point coordinates (wrapping), as a float.
#[inline(always)]
fn texel(t: &Texture, u: i32, v: i32) -> f32 {
    t.byte(u >> 16, v >> 16) as f32
}

/// Rock and caustic bytes at 16.16 fixed-point coordinates (wrapping), as floats.
#[inline(always)]
fn lit_texel(t: &LitTexture, u: i32, v: i32) -> (f32, f32) {
    let w = t.word(u >> 16, v >> 16);
    ((w & 0xFF) as f32, (w >> 8) as f32)
}

/// A 16.16 fixed-point texel coordinate along a run: `at + step * t` (wrapping).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Walk {
    pub(crate) at: i32,
    pub(crate) step: i32,
}

impl Walk {
    #[inline(always)]
    fn get(&self, t: i32) -> i32 {
        self.at.wrapping_add(self.step.wrapping_mul(t))
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

/// Runs the body on the parts `o` of a run of pixels `$out` from offset `$first`
/// (counted from the run's first node) that fall in one 16-pixel span each (`t0`: the
/// part's first pixel in its span, `span`: its nodes): a part span, whole spans (their
/// nodes from windows of the node arrays: no index or division per span), a part span.
/// A macro, not a function taking a closure: a closure does not inherit AVX2 from the
/// function it is written in, and the loop bodies must (45.1 vs 36.5 M instructions a
/// night-harbor frame).
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
        _ => match caustic {
            None => for_span_parts!(out, first, nodes, |o, t0, span| {
                let r = span.rock_run(rock);
                for (t, m) in o.iter_mut().enumerate() {
                    *m = rock_px(&r, (t0 + t) as i32);
                }
            }),
            Some(c) => for_span_parts!(out, first, nodes, |o, t0, span| {
                let r = span.caustic_run(c);
                for (t, m) in o.iter_mut().enumerate() {
                    *m = caustic_rock_px(&r, (t0 + t) as i32);
                }
            }),
        },
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
/// (three times faster than the four gathers a pixel group took on the AMD EPYC this was
/// measured on: 0.11 vs 0.37 ms for 100 000 x 4 lookups, min of 37 alternated runs).
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

/// floor() as an integer without a libm call (baseline x86-64 has no rounding
/// instruction); exact, like the packed build's rounding instruction.
#[inline(always)]
fn floor_i32(x: f32) -> i32 {
    let i = x as i32;
    i - ((i as f32) > x) as i32
}

// max then min, not clamp: a NaN lands on the bound, as the packed max/min do.
#[allow(clippy::manual_clamp)]
#[inline(always)]
fn plate_px(r: &PlateRun, t: f32) -> f32 {
    let inv = 1.0 / r.d.get(t);
    let u = r.nu.get(t) * inv;
    let v = r.nv.get(t) * inv;
    let cu = (u + r.half_marker) * r.cell_per_m;
    let cv = (r.half_marker - v) * r.cell_per_m;
    let (iu, iv) = (floor_i32(cu + 0.5), floor_i32(cv + 0.5));
    let au = ((iu as f32 - cu) * r.inv_wu + 0.5).max(0.0).min(1.0);
    let av = ((iv as f32 - cv) * r.inv_wv + 0.5).max(0.0).min(1.0);
    let left = av * r.cell(iu - 1, iv - 1) + (1.0 - av) * r.cell(iu - 1, iv);
    let right = av * r.cell(iu, iv - 1) + (1.0 - av) * r.cell(iu, iv);
    let albedo = au * left + (1.0 - au) * right;
    let c = match &r.caustic {
        Some(l) => {
            let k = l.texels_per_m;
            let (_, b) = lit_texel(l.tex, floor_i32(u * k) << 16, floor_i32(v * k) << 16);
            1.0 + l.strength * ((l.tex.caustic_offset + l.tex.caustic_scale * b) - 1.0)
        }
        None => 1.0,
    };
    albedo * (r.ambient.get(t) * c + r.lamp.get(t)) + r.add.get(t)
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
        _ => {
            for (t, m) in out.iter_mut().enumerate() {
                *m = plate_px(r, (first + t) as f32);
            }
        }
    }
}

/// The sensor's constants for one frame (see `sensor.rs`).
#[derive(Clone, Copy)]
pub(crate) struct SensorRow<'a> {
    pub(crate) read_var: f32,
    pub(crate) per_s: f32,
    pub(crate) top: f32,
    pub(crate) lut: &'a [u8; super::sensor::RESPONSE_LUT_LEN],
    /// A linear response computed instead of read from `lut`.
    pub(crate) linear: Option<super::sensor::Linear>,
}

#[inline(always)]
fn rock_px(r: &RockRun, t: i32) -> f32 {
    let tf = t as f32;
    texel(r.tex, r.u.get(t), r.v.get(t)) * r.light.get(tf) + r.add.get(tf)
}

#[inline(always)]
fn caustic_rock_px(r: &CausticRockRun, t: i32) -> f32 {
    let tf = t as f32;
    let (rb, cb) = lit_texel(r.tex, r.u.get(t), r.v.get(t));
    let albedo = r.tex.rock_offset + r.tex.rock_scale * rb;
    albedo * (r.light.get(tf) + r.caustic.get(tf) * cb) + r.add.get(tf)
}

#[inline(always)]
fn sensor_px(s: &SensorRow, m: f32, a: i16, b: i16) -> u8 {
    let g = (a as i32 + b as i32) as f32 * NOISE_SCALE;
    let v = (m.max(0.0) + s.read_var).sqrt() + g;
    if let Some(l) = &s.linear {
        return l.level(v, s.read_var);
    }
    // The 2^23 trick: adding 2^23 to a float in [0, 2^23) leaves the rounded integer in
    // its mantissa bits (what the packed build does too).
    let ix = ((v * s.per_s).max(0.0).min(s.top) + 8_388_608.0).to_bits() & 0x7F_FFFF;
    s.lut[ix as usize & (super::sensor::RESPONSE_LUT_LEN - 1)]
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
            let avx2 = std::arch::is_x86_feature_detected!("avx2");
            let avx512 = avx2
                && std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512bw")
                && std::arch::is_x86_feature_detected!("avx512vl")
                && std::arch::is_x86_feature_detected!("avx512vbmi");
            if want == Isa::Avx512 && avx512 {
                return Isa::Avx512;
            }
            if want != Isa::Portable && avx2 {
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
    let (out, mean, na, nb) = (&mut out[..n], &mean[..n], &noise[0][..n], &noise[1][..n]);
    match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: Avx2 (and Avx512) are only chosen when the CPU has them.
        Isa::Avx2 | Isa::Avx512 => unsafe {
            match &s.linear {
                Some(l) if isa == Isa::Avx512 => avx512::sensor_run_linear(out, mean, na, nb, s, l),
                Some(l) => avx2::sensor_run_linear(out, mean, na, nb, s, l),
                None => avx2::sensor_run(out, mean, na, nb, s),
            }
        },
        Isa::Portable => {
            for (((px, &m), &a), &b) in out.iter_mut().zip(mean).zip(na).zip(nb) {
                *px = sensor_px(s, m, a, b);
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::*;
    use std::arch::x86_64::*;

    #[inline(always)]
    unsafe fn lanes() -> __m256i {
        _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7)
    }

    #[inline(always)]
    unsafe fn walk(w: Walk, t: __m256i) -> __m256i {
        _mm256_add_epi32(
            _mm256_set1_epi32(w.at),
            _mm256_mullo_epi32(_mm256_set1_epi32(w.step), t),
        )
    }

    #[inline(always)]
    unsafe fn ramp(r: Ramp, t: __m256) -> __m256 {
        _mm256_add_ps(
            _mm256_set1_ps(r.at),
            _mm256_mul_ps(_mm256_set1_ps(r.step), t),
        )
    }

    /// Indices of the texels at eight 16.16 coordinates in a square texture of side
    /// `1 << log2` (wrapping).
    #[inline(always)]
    unsafe fn indices(log2: u32, u: __m256i, v: __m256i) -> [u32; 8] {
        let m = _mm256_set1_epi32(((1u32 << log2) - 1) as i32);
        let tx = _mm256_and_si256(_mm256_srai_epi32::<16>(u), m);
        let ty = _mm256_and_si256(_mm256_srai_epi32::<16>(v), m);
        let idx = _mm256_or_si256(_mm256_sll_epi32(ty, _mm_cvtsi32_si128(log2 as i32)), tx);
        let mut ix = [0u32; 8];
        _mm256_storeu_si256(ix.as_mut_ptr() as *mut __m256i, idx);
        ix
    }

    /// Eight texel bytes as floats. The caller guarantees `complete(tex)`.
    #[inline(always)]
    unsafe fn fetch(tex: &Texture, u: __m256i, v: __m256i) -> __m256 {
        // Scalar reads packed into one word (AVX2 gathers were slower on the AMD EPYC
        // this was tuned on).
        let ix = indices(tex.log2, u, v);
        let d = tex.data.as_ptr();
        let mut word = 0u64;
        for (k, &i) in ix.iter().enumerate() {
            word |= (*d.add(i as usize) as u64) << (8 * k);
        }
        _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_cvtsi64_si128(word as i64)))
    }

    /// Eight rock-and-caustic texels: (rock bytes, caustic bytes) as floats. The caller
    /// guarantees `complete_lit(tex)`.
    #[inline(always)]
    unsafe fn fetch_lit(tex: &LitTexture, u: __m256i, v: __m256i) -> (__m256, __m256) {
        let ix = indices(tex.log2, u, v);
        let d = tex.data.as_ptr();
        let (mut lo, mut hi) = (0u64, 0u64);
        for (k, &i) in ix.iter().enumerate() {
            let w = *d.add(i as usize) as u64;
            if k < 4 {
                lo |= w << (16 * k);
            } else {
                hi |= w << (16 * (k - 4));
            }
        }
        let w = _mm256_cvtepu16_epi32(_mm_set_epi64x(hi as i64, lo as i64));
        let rock = _mm256_and_si256(w, _mm256_set1_epi32(0xFF));
        let caustic = _mm256_srli_epi32::<8>(w);
        (_mm256_cvtepi32_ps(rock), _mm256_cvtepi32_ps(caustic))
    }

    /// Runs inside `rock_nodes_run` (AVX2 enabled there).
    #[inline(always)]
    pub(super) unsafe fn rock_span(out: &mut [f32], first: usize, r: &RockRun) {
        let n = out.len();
        let mut t0 = 0usize;
        while t0 + 8 <= n {
            let ti = _mm256_add_epi32(_mm256_set1_epi32((first + t0) as i32), lanes());
            let tf = _mm256_cvtepi32_ps(ti);
            let b = fetch(r.tex, walk(r.u, ti), walk(r.v, ti));
            let m = _mm256_add_ps(_mm256_mul_ps(b, ramp(r.light, tf)), ramp(r.add, tf));
            _mm256_storeu_ps(out.as_mut_ptr().add(t0), m);
            t0 += 8;
        }
        for (t, m) in out.iter_mut().enumerate().skip(t0) {
            *m = rock_px(r, (first + t) as i32);
        }
    }

    #[inline(always)]
    pub(super) unsafe fn caustic_rock_span(out: &mut [f32], first: usize, r: &CausticRockRun) {
        let n = out.len();
        let mut t0 = 0usize;
        let (ro, rs) = (
            _mm256_set1_ps(r.tex.rock_offset),
            _mm256_set1_ps(r.tex.rock_scale),
        );
        while t0 + 8 <= n {
            let ti = _mm256_add_epi32(_mm256_set1_epi32((first + t0) as i32), lanes());
            let tf = _mm256_cvtepi32_ps(ti);
            let (rb, cb) = fetch_lit(r.tex, walk(r.u, ti), walk(r.v, ti));
            let albedo = _mm256_add_ps(ro, _mm256_mul_ps(rs, rb));
            let light = _mm256_add_ps(ramp(r.light, tf), _mm256_mul_ps(ramp(r.caustic, tf), cb));
            let m = _mm256_add_ps(_mm256_mul_ps(albedo, light), ramp(r.add, tf));
            _mm256_storeu_ps(out.as_mut_ptr().add(t0), m);
            t0 += 8;
        }
        for (t, m) in out.iter_mut().enumerate().skip(t0) {
            *m = caustic_rock_px(r, (first + t) as i32);
        }
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn rock_nodes_run(
        out: &mut [f32],
        first: usize,
        nodes: &RockNodes,
        rock: &Texture,
        caustic: Option<&LitTexture>,
    ) {
        // One loop per texture kind, not a branch per span.
        match caustic {
            None => for_span_parts!(out, first, nodes, |o, t0, span| {
                rock_span(o, t0, &span.rock_run(rock))
            }),
            Some(c) => for_span_parts!(out, first, nodes, |o, t0, span| {
                caustic_rock_span(o, t0, &span.caustic_run(c))
            }),
        }
    }

    /// Share of the pixel footprint on the lower cell: `(i - c) / w + 0.5` in [0, 1].
    #[inline(always)]
    unsafe fn box_weight(i: __m256i, c: __m256, inv_w: __m256) -> __m256 {
        let x = _mm256_mul_ps(_mm256_sub_ps(_mm256_cvtepi32_ps(i), c), inv_w);
        let x = _mm256_max_ps(_mm256_add_ps(x, _mm256_set1_ps(0.5)), _mm256_setzero_ps());
        _mm256_min_ps(x, _mm256_set1_ps(1.0))
    }

    #[inline(always)]
    unsafe fn floor_epi32(x: __m256) -> __m256i {
        _mm256_cvttps_epi32(_mm256_floor_ps(x))
    }

    /// floor(x) as a 16.16 fixed-point texel coordinate (what `fetch` takes).
    #[inline(always)]
    unsafe fn fixed_floor(x: __m256) -> __m256i {
        _mm256_slli_epi32::<16>(floor_epi32(x))
    }

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

    /// `CellRows` in registers: rows 0-7, rows 8-15, black, white.
    type RowRegs = (__m256i, __m256i, __m256, __m256);

    #[inline(always)]
    unsafe fn row_regs(rows: &CellRows) -> RowRegs {
        (
            _mm256_loadu_si256(rows.bits.as_ptr() as *const __m256i),
            _mm256_loadu_si256(rows.bits.as_ptr().add(8) as *const __m256i),
            _mm256_set1_ps(rows.black),
            _mm256_set1_ps(rows.white),
        )
    }

    /// `cell` from the bits: the same clamped cell, the same albedo.
    #[inline(always)]
    unsafe fn cell_of(r: &PlateRun, regs: Option<RowRegs>, ci: __m256i, cj: __m256i) -> __m256 {
        let Some((lo_rows, hi_rows, black, white)) = regs else {
            return cell(r, ci, cj);
        };
        let (lo, hi) = (_mm256_set1_epi32(-1), _mm256_set1_epi32(r.side - 2));
        let one = _mm256_set1_epi32(1);
        let c = _mm256_add_epi32(_mm256_min_epi32(_mm256_max_epi32(ci, lo), hi), one);
        let row = _mm256_add_epi32(_mm256_min_epi32(_mm256_max_epi32(cj, lo), hi), one);
        // The row's bits: from the first register for rows 0-7, the second for 8-15
        // (a permute reads the index's low three bits).
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

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn plate_run(out: &mut [f32], first: usize, r: &PlateRun) {
        let regs = r.rows.map(|rows| row_regs(rows));
        let n = out.len();
        let (one, half) = (_mm256_set1_ps(1.0), _mm256_set1_ps(0.5));
        let (hm, cpm) = (_mm256_set1_ps(r.half_marker), _mm256_set1_ps(r.cell_per_m));
        let (iwu, iwv) = (_mm256_set1_ps(r.inv_wu), _mm256_set1_ps(r.inv_wv));
        let ione = _mm256_set1_epi32(1);
        let mut t0 = 0usize;
        while t0 + 8 <= n {
            let ti = _mm256_add_epi32(_mm256_set1_epi32((first + t0) as i32), lanes());
            let t = _mm256_cvtepi32_ps(ti);
            let inv = _mm256_div_ps(one, ramp(r.d, t));
            let u = _mm256_mul_ps(ramp(r.nu, t), inv);
            let v = _mm256_mul_ps(ramp(r.nv, t), inv);
            let cu = _mm256_mul_ps(_mm256_add_ps(u, hm), cpm);
            let cv = _mm256_mul_ps(_mm256_sub_ps(hm, v), cpm);
            let iu = floor_epi32(_mm256_add_ps(cu, half));
            let iv = floor_epi32(_mm256_add_ps(cv, half));
            let (au, av) = (box_weight(iu, cu, iwu), box_weight(iv, cv, iwv));
            let (iu1, iv1) = (_mm256_sub_epi32(iu, ione), _mm256_sub_epi32(iv, ione));
            let nav = _mm256_sub_ps(one, av);
            let left = _mm256_add_ps(
                _mm256_mul_ps(av, cell_of(r, regs, iu1, iv1)),
                _mm256_mul_ps(nav, cell_of(r, regs, iu1, iv)),
            );
            let right = _mm256_add_ps(
                _mm256_mul_ps(av, cell_of(r, regs, iu, iv1)),
                _mm256_mul_ps(nav, cell_of(r, regs, iu, iv)),
            );
            let albedo = _mm256_add_ps(
                _mm256_mul_ps(au, left),
                _mm256_mul_ps(_mm256_sub_ps(one, au), right),
            );
            let c = match &r.caustic {
                Some(l) => {
                    let k = _mm256_set1_ps(l.texels_per_m);
                    let (_, b0) = fetch_lit(
                        l.tex,
                        fixed_floor(_mm256_mul_ps(u, k)),
                        fixed_floor(_mm256_mul_ps(v, k)),
                    );
                    let (to, ts) = (
                        _mm256_set1_ps(l.tex.caustic_offset),
                        _mm256_set1_ps(l.tex.caustic_scale),
                    );
                    let b = _mm256_add_ps(to, _mm256_mul_ps(ts, b0));
                    _mm256_add_ps(
                        one,
                        _mm256_mul_ps(_mm256_set1_ps(l.strength), _mm256_sub_ps(b, one)),
                    )
                }
                None => one,
            };
            let light = _mm256_add_ps(_mm256_mul_ps(ramp(r.ambient, t), c), ramp(r.lamp, t));
            let m = _mm256_add_ps(_mm256_mul_ps(albedo, light), ramp(r.add, t));
            _mm256_storeu_ps(out.as_mut_ptr().add(t0), m);
            t0 += 8;
        }
        for (t, m) in out.iter_mut().enumerate().skip(t0) {
            *m = plate_px(r, (first + t) as f32);
        }
    }

    /// The square-root-domain signal `s` of pixels `t0..t0 + 8`: mean electrons and the
    /// two noise windows in (see `sensor_px`). max(m, 0) like f32::max: a NaN mean gives
    /// 0 (the second operand).
    #[inline(always)]
    unsafe fn signal_s(mean: &[f32], na: &[i16], nb: &[i16], t0: usize, rv: __m256) -> __m256 {
        let m = _mm256_loadu_ps(mean.as_ptr().add(t0));
        let ga = _mm256_cvtepi16_epi32(_mm_loadu_si128(na.as_ptr().add(t0) as *const __m128i));
        let gb = _mm256_cvtepi16_epi32(_mm_loadu_si128(nb.as_ptr().add(t0) as *const __m128i));
        let g = _mm256_mul_ps(
            _mm256_cvtepi32_ps(_mm256_add_epi32(ga, gb)),
            _mm256_set1_ps(NOISE_SCALE),
        );
        let m0 = _mm256_max_ps(m, _mm256_setzero_ps());
        _mm256_add_ps(_mm256_sqrt_ps(_mm256_add_ps(m0, rv)), g)
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn sensor_run(
        out: &mut [u8],
        mean: &[f32],
        na: &[i16],
        nb: &[i16],
        s: &SensorRow,
    ) {
        let n = out.len();
        let zero = _mm256_setzero_ps();
        let (rv, per_s, top) = (
            _mm256_set1_ps(s.read_var),
            _mm256_set1_ps(s.per_s),
            _mm256_set1_ps(s.top),
        );
        let (magic, mant) = (
            _mm256_set1_ps(8_388_608.0),
            _mm256_set1_epi32(0x7F_FFFF & (super::super::sensor::RESPONSE_LUT_LEN as i32 - 1)),
        );
        let mut idx = [0u32; 8];
        let mut t0 = 0usize;
        while t0 + 8 <= n {
            let v = signal_s(mean, na, nb, t0, rv);
            let x = _mm256_min_ps(_mm256_max_ps(_mm256_mul_ps(v, per_s), zero), top);
            let ix = _mm256_and_si256(_mm256_castps_si256(_mm256_add_ps(x, magic)), mant);
            _mm256_storeu_si256(idx.as_mut_ptr() as *mut __m256i, ix);
            // Eight table reads into one 8-byte store.
            let mut word = 0u64;
            for (k, &i) in idx.iter().enumerate() {
                let level = s.lut[i as usize & (super::super::sensor::RESPONSE_LUT_LEN - 1)];
                word |= (level as u64) << (8 * k);
            }
            out[t0..t0 + 8].copy_from_slice(&word.to_le_bytes());
            t0 += 8;
        }
        for t in t0..n {
            out[t] = sensor_px(s, mean[t], na[t], nb[t]);
        }
    }

    /// `sensor_run` for a linear response: the level computed (`Linear::level`, same
    /// operations in the same order) and packed to bytes, no table read.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn sensor_run_linear(
        out: &mut [u8],
        mean: &[f32],
        na: &[i16],
        nb: &[i16],
        s: &SensorRow,
        l: &super::super::sensor::Linear,
    ) {
        let n = out.len();
        let zero = _mm256_setzero_ps();
        let rv = _mm256_set1_ps(s.read_var);
        let (fw, per_e, top) = (
            _mm256_set1_ps(l.full_well_e),
            _mm256_set1_ps(l.per_e),
            _mm256_set1_ps(255.0),
        );
        let (magic, byte) = (_mm256_set1_ps(8_388_608.0), _mm256_set1_epi32(0xFF));
        // The level (0..=255 in i32 lanes) of pixels t0..t0 + 8.
        let level = |t0: usize| {
            let v = _mm256_max_ps(signal_s(mean, na, nb, t0, rv), zero);
            let e = _mm256_min_ps(
                _mm256_max_ps(_mm256_sub_ps(_mm256_mul_ps(v, v), rv), zero),
                fw,
            );
            let y = _mm256_min_ps(_mm256_mul_ps(e, per_e), top);
            _mm256_and_si256(_mm256_castps_si256(_mm256_add_ps(y, magic)), byte)
        };
        let mut t0 = 0usize;
        // Sixteen pixels a step: two packs and one permute put both groups' levels in
        // order in the low 16 bytes (one store, half the loop's bookkeeping).
        let order = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
        while t0 + 16 <= n {
            let (a, b) = (level(t0), level(t0 + 8));
            let p8 = _mm256_packus_epi16(_mm256_packus_epi32(a, b), _mm256_setzero_si256());
            let bytes = _mm256_permutevar8x32_epi32(p8, order);
            _mm_storeu_si128(
                out.as_mut_ptr().add(t0) as *mut __m128i,
                _mm256_castsi256_si128(bytes),
            );
            t0 += 16;
        }
        while t0 + 8 <= n {
            let q = level(t0);
            // Eight levels (0..=255 in i32 lanes) to eight bytes.
            let p16 = _mm256_packus_epi32(q, q);
            let p8 = _mm256_packus_epi16(p16, p16);
            let b = _mm_unpacklo_epi32(
                _mm256_castsi256_si128(p8),
                _mm256_extracti128_si256::<1>(p8),
            );
            _mm_storel_epi64(out.as_mut_ptr().add(t0) as *mut __m128i, b);
            t0 += 8;
        }
        for t in t0..n {
            out[t] = sensor_px(s, mean[t], na[t], nb[t]);
        }
    }
}

/// The AVX-512 build: rock, plate and linear sensor sixteen pixels a step (the others
/// are the AVX2 loops). The rock takes one whole span a step. Where a span's texels lie in
/// two texture rows of 64 bytes (the usual case: a span covers about nine texels at 1 m),
/// both rows are loaded and one two-register byte permute (AVX-512 VBMI) picks the
/// sixteen texels; elsewhere they are read one by one. On the AMD EPYC this was measured
/// on, gathers (microcoded there) and sixteen-lane scalar reads were no faster than the
/// AVX2 loop; the windows took a render bench frame to 0.83-0.87x. Same f32 operations
/// in the same order as the other builds.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::*;
    use std::arch::x86_64::*;

    #[inline(always)]
    unsafe fn lanes() -> __m512i {
        _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15)
    }

    #[inline(always)]
    unsafe fn walk(w: Walk, t: __m512i) -> __m512i {
        _mm512_add_epi32(
            _mm512_set1_epi32(w.at),
            _mm512_mullo_epi32(_mm512_set1_epi32(w.step), t),
        )
    }

    #[inline(always)]
    unsafe fn ramp(r: Ramp, t: __m512) -> __m512 {
        _mm512_add_ps(
            _mm512_set1_ps(r.at),
            _mm512_mul_ps(_mm512_set1_ps(r.step), t),
        )
    }

    /// Texel indices at sixteen 16.16 coordinates in a square texture of side
    /// `1 << log2` (wrapping).
    #[inline(always)]
    unsafe fn indices(log2: u32, u: __m512i, v: __m512i) -> __m512i {
        let m = _mm512_set1_epi32(((1u32 << log2) - 1) as i32);
        let tx = _mm512_and_si512(_mm512_srai_epi32::<16>(u), m);
        let ty = _mm512_and_si512(_mm512_srai_epi32::<16>(v), m);
        _mm512_or_si512(_mm512_sll_epi32(ty, _mm_cvtsi32_si128(log2 as i32)), tx)
    }

    /// Sixteen texel bytes as floats. The caller guarantees `complete(tex)`.
    #[inline(always)]
    unsafe fn fetch(tex: &Texture, u: __m512i, v: __m512i) -> __m512 {
        let mut ix = [0u32; 16];
        _mm512_storeu_si512(ix.as_mut_ptr() as *mut __m512i, indices(tex.log2, u, v));
        let d = tex.data.as_ptr();
        let (mut lo, mut hi) = (0u64, 0u64);
        for k in 0..8 {
            lo |= (*d.add(ix[k] as usize) as u64) << (8 * k);
            hi |= (*d.add(ix[k + 8] as usize) as u64) << (8 * k);
        }
        _mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(_mm_set_epi64x(hi as i64, lo as i64)))
    }

    /// Sixteen rock-and-caustic texels: (rock bytes, caustic bytes) as floats. The
    /// caller guarantees `complete_lit(tex)`.
    #[inline(always)]
    unsafe fn fetch_lit(tex: &LitTexture, u: __m512i, v: __m512i) -> (__m512, __m512) {
        let mut ix = [0u32; 16];
        _mm512_storeu_si512(ix.as_mut_ptr() as *mut __m512i, indices(tex.log2, u, v));
        let d = tex.data.as_ptr();
        let mut q = [0u64; 4];
        for k in 0..4 {
            for (j, w) in q.iter_mut().enumerate() {
                *w |= (*d.add(ix[4 * j + k] as usize) as u64) << (16 * k);
            }
        }
        let lo = _mm256_set_epi64x(q[3] as i64, q[2] as i64, q[1] as i64, q[0] as i64);
        let w = _mm512_cvtepu16_epi32(lo);
        let rock = _mm512_and_si512(w, _mm512_set1_epi32(0xFF));
        let caustic = _mm512_srli_epi32::<8>(w);
        (_mm512_cvtepi32_ps(rock), _mm512_cvtepi32_ps(caustic))
    }

    /// The lowest and highest whole texel a walk reaches over a span's 16 pixels, or
    /// None where `at + step * t` leaves i32 (the lanes wrap there, so they are not
    /// monotonic).
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

    /// Where a span's texels lie in a window of two texture rows, `width` texels wide:
    /// the two rows' first texel indices, and the lane offsets that turn a lane's
    /// whole texel (u, v) into its place in the window (`u - du`, `(v - vlo) * width`).
    /// None where the span reaches wider, over more than two rows, or across the
    /// texture's edge in u.
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
    /// two-register byte permute instead of sixteen reads (see `span_window`). The
    /// caller guarantees `complete(tex)`; `tu`, `tv` are `walk(u)`, `walk(v)`.
    #[inline(always)]
    unsafe fn fetch_window(
        tex: &Texture,
        u: Walk,
        v: Walk,
        tu: __m512i,
        tv: __m512i,
    ) -> Option<__m512> {
        let (r0, r1, du, vlo) = span_window(tex.log2, u, v, 64)?;
        let d = tex.data.as_ptr();
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

    /// `fetch_lit` from a window of two rows of 32 texels (two-register word permute).
    #[inline(always)]
    unsafe fn fetch_lit_window(
        tex: &LitTexture,
        u: Walk,
        v: Walk,
        tu: __m512i,
        tv: __m512i,
    ) -> Option<(__m512, __m512)> {
        let (r0, r1, du, vlo) = span_window(tex.log2, u, v, 32)?;
        let d = tex.data.as_ptr();
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

    #[inline(always)]
    unsafe fn rock_span(out: &mut [f32], first: usize, r: &RockRun) {
        if out.len() != 16 || first != 0 {
            return super::avx2::rock_span(out, first, r);
        }
        let ti = lanes();
        let tf = _mm512_cvtepi32_ps(ti);
        let (tu, tv) = (walk(r.u, ti), walk(r.v, ti));
        let b = match fetch_window(r.tex, r.u, r.v, tu, tv) {
            Some(b) => b,
            None => fetch(r.tex, tu, tv),
        };
        let m = _mm512_add_ps(_mm512_mul_ps(b, ramp(r.light, tf)), ramp(r.add, tf));
        _mm512_storeu_ps(out.as_mut_ptr(), m);
    }

    #[inline(always)]
    unsafe fn caustic_rock_span(out: &mut [f32], first: usize, r: &CausticRockRun) {
        if out.len() != 16 || first != 0 {
            return super::avx2::caustic_rock_span(out, first, r);
        }
        let ti = lanes();
        let tf = _mm512_cvtepi32_ps(ti);
        let (ro, rs) = (
            _mm512_set1_ps(r.tex.rock_offset),
            _mm512_set1_ps(r.tex.rock_scale),
        );
        let (tu, tv) = (walk(r.u, ti), walk(r.v, ti));
        let (rb, cb) = match fetch_lit_window(r.tex, r.u, r.v, tu, tv) {
            Some(t) => t,
            None => fetch_lit(r.tex, tu, tv),
        };
        let albedo = _mm512_add_ps(ro, _mm512_mul_ps(rs, rb));
        let light = _mm512_add_ps(ramp(r.light, tf), _mm512_mul_ps(ramp(r.caustic, tf), cb));
        let m = _mm512_add_ps(_mm512_mul_ps(albedo, light), ramp(r.add, tf));
        _mm512_storeu_ps(out.as_mut_ptr(), m);
    }

    /// Share of the pixel footprint on the lower cell (see the AVX2 `box_weight`).
    #[inline(always)]
    unsafe fn box_weight(i: __m512i, c: __m512, inv_w: __m512) -> __m512 {
        let x = _mm512_mul_ps(_mm512_sub_ps(_mm512_cvtepi32_ps(i), c), inv_w);
        let x = _mm512_max_ps(_mm512_add_ps(x, _mm512_set1_ps(0.5)), _mm512_setzero_ps());
        _mm512_min_ps(x, _mm512_set1_ps(1.0))
    }

    #[inline(always)]
    unsafe fn floor_epi32(x: __m512) -> __m512i {
        _mm512_cvttps_epi32(_mm512_roundscale_ps::<
            { _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC },
        >(x))
    }

    #[inline(always)]
    unsafe fn clamp(x: __m512i, lo: i32, hi: i32) -> __m512i {
        _mm512_min_epi32(
            _mm512_max_epi32(x, _mm512_set1_epi32(lo)),
            _mm512_set1_epi32(hi),
        )
    }

    /// The plate sixteen pixels a step: the four cells around a pixel from one permute
    /// of the paired rows (`CellRows::pairs`) and two shifts, where the AVX2 loop takes
    /// two permutes, a blend and a shift per cell. The caller guarantees
    /// `r.gather_safe()` and the pairs.
    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl,avx512vbmi")]
    pub(super) unsafe fn plate_run(out: &mut [f32], first: usize, r: &PlateRun) {
        let Some(rows) = r.rows else {
            return super::avx2::plate_run(out, first, r);
        };
        let Some(pairs) = rows.pairs else {
            return super::avx2::plate_run(out, first, r);
        };
        let pairs = _mm512_loadu_si512(pairs.as_ptr() as *const __m512i);
        let (black, white) = (_mm512_set1_ps(rows.black), _mm512_set1_ps(rows.white));
        let n = out.len();
        let side = r.side;
        let (one, half) = (_mm512_set1_ps(1.0), _mm512_set1_ps(0.5));
        let (hm, cpm) = (_mm512_set1_ps(r.half_marker), _mm512_set1_ps(r.cell_per_m));
        let (iwu, iwv) = (_mm512_set1_ps(r.inv_wu), _mm512_set1_ps(r.inv_wv));
        let (lo_bit, hi_bit) = (_mm512_set1_epi32(1), _mm512_set1_epi32(1 << 16));
        let mut t0 = 0usize;
        while t0 + 16 <= n {
            let ti = _mm512_add_epi32(_mm512_set1_epi32((first + t0) as i32), lanes());
            let t = _mm512_cvtepi32_ps(ti);
            let inv = _mm512_div_ps(one, ramp(r.d, t));
            let u = _mm512_mul_ps(ramp(r.nu, t), inv);
            let v = _mm512_mul_ps(ramp(r.nv, t), inv);
            let cu = _mm512_mul_ps(_mm512_add_ps(u, hm), cpm);
            let cv = _mm512_mul_ps(_mm512_sub_ps(hm, v), cpm);
            let iu = floor_epi32(_mm512_add_ps(cu, half));
            let iv = floor_epi32(_mm512_add_ps(cv, half));
            let (au, av) = (box_weight(iu, cu, iwu), box_weight(iv, cv, iwv));
            // Rows of cells iv - 1 (low half) and iv (high half), then the columns of
            // cells iu - 1 and iu as `cell` clamps them.
            let pair =
                _mm512_permutexvar_epi32(clamp(_mm512_add_epi32(iv, lo_bit), 0, side), pairs);
            let c0 = clamp(iu, 0, side - 1);
            let c1 = clamp(_mm512_add_epi32(iu, lo_bit), 0, side - 1);
            let (w0, w1) = (_mm512_srlv_epi32(pair, c0), _mm512_srlv_epi32(pair, c1));
            let cell = |w: __m512i, bit: __m512i| {
                _mm512_mask_blend_ps(_mm512_test_epi32_mask(w, bit), black, white)
            };
            let nav = _mm512_sub_ps(one, av);
            let left = _mm512_add_ps(
                _mm512_mul_ps(av, cell(w0, lo_bit)),
                _mm512_mul_ps(nav, cell(w0, hi_bit)),
            );
            let right = _mm512_add_ps(
                _mm512_mul_ps(av, cell(w1, lo_bit)),
                _mm512_mul_ps(nav, cell(w1, hi_bit)),
            );
            let albedo = _mm512_add_ps(
                _mm512_mul_ps(au, left),
                _mm512_mul_ps(_mm512_sub_ps(one, au), right),
            );
            let c = match &r.caustic {
                Some(l) => {
                    let k = _mm512_set1_ps(l.texels_per_m);
                    let fixed =
                        |x: __m512| _mm512_slli_epi32::<16>(floor_epi32(_mm512_mul_ps(x, k)));
                    let (_, b0) = fetch_lit(l.tex, fixed(u), fixed(v));
                    let (to, ts) = (
                        _mm512_set1_ps(l.tex.caustic_offset),
                        _mm512_set1_ps(l.tex.caustic_scale),
                    );
                    let b = _mm512_add_ps(to, _mm512_mul_ps(ts, b0));
                    _mm512_add_ps(
                        one,
                        _mm512_mul_ps(_mm512_set1_ps(l.strength), _mm512_sub_ps(b, one)),
                    )
                }
                None => one,
            };
            let light = _mm512_add_ps(_mm512_mul_ps(ramp(r.ambient, t), c), ramp(r.lamp, t));
            let m = _mm512_add_ps(_mm512_mul_ps(albedo, light), ramp(r.add, t));
            _mm512_storeu_ps(out.as_mut_ptr().add(t0), m);
            t0 += 16;
        }
        if t0 < n {
            super::avx2::plate_run(&mut out[t0..], first + t0, r);
        }
    }

    /// The linear sensor sixteen pixels a step (see the AVX2 `sensor_run_linear`): the
    /// levels narrow to bytes in one instruction.
    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl,avx512vbmi")]
    pub(super) unsafe fn sensor_run_linear(
        out: &mut [u8],
        mean: &[f32],
        na: &[i16],
        nb: &[i16],
        s: &SensorRow,
        l: &super::super::sensor::Linear,
    ) {
        let n = out.len().min(mean.len()).min(na.len()).min(nb.len());
        let zero = _mm512_setzero_ps();
        let rv = _mm512_set1_ps(s.read_var);
        let (fw, per_e, top) = (
            _mm512_set1_ps(l.full_well_e),
            _mm512_set1_ps(l.per_e),
            _mm512_set1_ps(255.0),
        );
        let (magic, byte, scale) = (
            _mm512_set1_ps(8_388_608.0),
            _mm512_set1_epi32(0xFF),
            _mm512_set1_ps(NOISE_SCALE),
        );
        let mut t0 = 0usize;
        while t0 + 16 <= n {
            let m = _mm512_loadu_ps(mean.as_ptr().add(t0));
            let ga =
                _mm512_cvtepi16_epi32(_mm256_loadu_si256(na.as_ptr().add(t0) as *const __m256i));
            let gb =
                _mm512_cvtepi16_epi32(_mm256_loadu_si256(nb.as_ptr().add(t0) as *const __m256i));
            let g = _mm512_mul_ps(_mm512_cvtepi32_ps(_mm512_add_epi32(ga, gb)), scale);
            let m0 = _mm512_max_ps(m, zero);
            let v = _mm512_add_ps(_mm512_sqrt_ps(_mm512_add_ps(m0, rv)), g);
            let v = _mm512_max_ps(v, zero);
            let e = _mm512_min_ps(
                _mm512_max_ps(_mm512_sub_ps(_mm512_mul_ps(v, v), rv), zero),
                fw,
            );
            let y = _mm512_min_ps(_mm512_mul_ps(e, per_e), top);
            let q = _mm512_and_si512(_mm512_castps_si512(_mm512_add_ps(y, magic)), byte);
            _mm_storeu_si128(
                out.as_mut_ptr().add(t0) as *mut __m128i,
                _mm512_cvtepi32_epi8(q),
            );
            t0 += 16;
        }
        if t0 < n {
            super::avx2::sensor_run_linear(
                &mut out[t0..n],
                &mean[t0..n],
                &na[t0..n],
                &nb[t0..n],
                s,
                l,
            );
        }
    }

    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl,avx512vbmi")]
    pub(super) unsafe fn rock_nodes_run(
        out: &mut [f32],
        first: usize,
        nodes: &RockNodes,
        rock: &Texture,
        caustic: Option<&LitTexture>,
    ) {
        match caustic {
            None => for_span_parts!(out, first, nodes, |o, t0, span| {
                rock_span(o, t0, &span.rock_run(rock))
            }),
            Some(c) => for_span_parts!(out, first, nodes, |o, t0, span| {
                caustic_rock_span(o, t0, &span.caustic_run(c))
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The macro's parts tile the run as one read per pixel would: pixel `p` in span
    /// `(first + p) / 16` at offset `(first + p) % 16`, up to the last span.
    #[test]
    fn span_parts_tile_the_run() {
        let cells = vec![[0f32; 6]; 12];
        let walks: Vec<i32> = (0..12).collect();
        let nodes = RockNodes {
            cells: &cells,
            fy: 0.0,
            walks: [&walks, &walks],
        };
        for first in [0usize, 1, 7, 15, 16, 17, 40, 170, 176, 200] {
            for len in [0usize, 1, 8, 15, 16, 17, 31, 32, 33, 100, 200] {
                let mut out = vec![0f32; len];
                // Each pixel records its span (the node walk at the span's start) + 1 and its
                // offset in the span, written through the part it was given.
                let mut seen = vec![(0i32, 0usize); len];
                let base = out.as_ptr() as usize;
                for_span_parts!(&mut out, first, &nodes, |o, t0, span| {
                    let at = (o.as_ptr() as usize - base) / 4;
                    for k in 0..o.len() {
                        seen[at + k] = (span.walks[0][0] + 1, t0 + k);
                    }
                });
                for (p, &got) in seen.iter().enumerate() {
                    let pos = first + p;
                    let want = if pos / 16 < cells.len() - 1 {
                        (pos as i32 / 16 + 1, pos % 16)
                    } else {
                        (0, 0)
                    };
                    assert_eq!(got, want, "first {first} len {len} pixel {p}");
                }
            }
        }
    }

    /// The packed sensor loops (AVX-512 16, AVX2 16, then 8 pixels a step, then one) give the portable
    /// loop's levels at every row length, for a table and a computed linear response,
    /// over means from below zero to past the full well.
    #[test]
    #[cfg_attr(
        not(build_host_avx2),
        ignore = "the build host has no AVX2: nothing packed"
    )]
    fn packed_sensor_matches_portable_at_every_length() {
        assert_ne!(
            Isa::detect(false),
            Isa::Portable,
            "this CPU runs no packed loops, though the build host did"
        );
        let mut lut = Box::new([0u8; super::super::sensor::RESPONSE_LUT_LEN]);
        let last = lut.len() - 1;
        for (i, l) in lut.iter_mut().enumerate() {
            *l = ((i * 255) / last) as u8 ^ (i as u8 & 3);
        }
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let n = 70;
        let mean: Vec<f32> = (0..n).map(|_| (next() % 24_000) as f32 - 500.0).collect();
        let na: Vec<i16> = (0..n).map(|_| (next() % 8001) as i16 - 4000).collect();
        let nb: Vec<i16> = (0..n).map(|_| (next() % 8001) as i16 - 4000).collect();
        let linear = super::super::sensor::Linear {
            per_e: 255.0 * 4.0 / 20_000.0,
            full_well_e: 20_000.0,
        };
        for lin in [None, Some(linear)] {
            let s = SensorRow {
                read_var: 9.0,
                per_s: 4095.0 / 150.0,
                top: 4095.0,
                lut: &lut,
                linear: lin,
            };
            for len in 0..=n {
                let (m, a, b) = (&mean[..len], &na[..len], &nb[..len]);
                let mut portable = vec![0u8; len];
                sensor_run(Isa::Portable, &mut portable, m, [a, b], &s);
                for isa in [Isa::Avx2, Isa::Avx512].map(Isa::best_up_to) {
                    let mut packed = vec![0u8; len];
                    sensor_run(isa, &mut packed, m, [a, b], &s);
                    let linear = lin.is_some();
                    assert_eq!(packed, portable, "{isa:?} length {len}, linear {linear}");
                }
                assert!(portable.iter().any(|&v| v > 0) || len < 8, "length {len}");
            }
        }
    }

    /// Every packed rock loop gives the portable loop's values, with and without
    /// caustics, over walks that fit the AVX-512 build's two-row windows and walks that
    /// do not (too wide, three rows, across the texture's edge, past i32), at run
    /// offsets that leave part spans.
    #[test]
    #[cfg_attr(
        not(build_host_avx2),
        ignore = "the build host has no AVX2: nothing packed"
    )]
    fn packed_rock_loops_match_portable_over_all_kinds_of_walks() {
        let mut x = 0x2545_F491_4F6C_DD1Du64;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let log2 = 7;
        let n = 1usize << (2 * log2);
        let rock = Texture {
            log2,
            data: (0..n).map(|_| next() as u8).collect(),
            scale: 0.01,
            offset: 0.2,
        };
        let lit = LitTexture {
            log2,
            data: (0..n).map(|_| next() as u16).collect(),
            rock_scale: 0.01,
            rock_offset: 0.2,
            caustic_scale: 0.004,
            caustic_offset: 0.5,
        };
        let side = 1i32 << log2;
        let nodes = 40;
        let cells: Vec<[f32; 6]> = (0..nodes)
            .map(|_| std::array::from_fn(|_| (next() % 1000) as f32 * 0.37))
            .collect();
        let mut builds = Vec::new();
        for kind in 0..6 {
            // Texel steps a pixel (16.16) and a start for each kind of walk.
            let (su, sv, at_u, at_v): (i32, i32, i32, i32) = match kind {
                0 => (45_000, 1_500, 3 << 16, 7 << 16),     // fits a window
                1 => (-52_000, -2_000, 90 << 16, 40 << 16), // fits, walking back
                2 => (300_000, 100, 0, 0),                  // too wide
                3 => (20_000, 30_000, 0, 0),                // over three rows
                4 => (60_000, 0, (side - 5) << 16, 0),      // across the edge in u
                _ => (40_000, 0, i32::MAX - (2 << 16), 0),  // leaves i32
            };
            let wu: Vec<i32> = (0..nodes as i32)
                .map(|k| at_u.wrapping_add(su.wrapping_mul(16 * k)))
                .collect();
            let wv: Vec<i32> = (0..nodes as i32)
                .map(|k| at_v.wrapping_add(sv.wrapping_mul(16 * k)))
                .collect();
            let run = RockNodes {
                cells: &cells,
                fy: 0.3,
                walks: [&wu, &wv],
            };
            // The kinds meant to fit the windows do, the others do not.
            #[cfg(target_arch = "x86_64")]
            for width in [64, 32] {
                let (u, v) = (
                    Walk {
                        at: wu[0],
                        step: su,
                    },
                    Walk {
                        at: wv[0],
                        step: sv,
                    },
                );
                let fits = avx512::span_window(log2, u, v, width).is_some();
                assert_eq!(fits, kind < 2, "kind {kind} width {width}");
            }
            for c in [None, Some(&lit)] {
                for (first, len) in [(0usize, 16 * (nodes - 1)), (5, 300), (16, 17), (3, 9)] {
                    let mut want = vec![0f32; len];
                    rock_nodes_run(Isa::Portable, &mut want, first, &run, &rock, c);
                    for isa in [Isa::Avx2, Isa::Avx512].map(Isa::best_up_to) {
                        let mut got = vec![0f32; len];
                        rock_nodes_run(isa, &mut got, first, &run, &rock, c);
                        let same = got
                            .iter()
                            .zip(&want)
                            .all(|(a, b)| a.to_bits() == b.to_bits());
                        assert!(
                            same,
                            "{isa:?} kind {kind} caustic {} first {first}",
                            c.is_some()
                        );
                        builds.push(isa);
                    }
                }
            }
        }
        assert!(builds.iter().any(|&b| b != Isa::Portable));
    }

    /// Every packed plate loop gives the portable loop's values, bit for bit: runs that
    /// cross the whole table and its border on both sides (the clamped cells), at
    /// lengths that leave 8-pixel and scalar tails, with and without caustics, for the
    /// table as bits (with and without the AVX-512 row pairs) and as gathered cells.
    #[test]
    #[cfg_attr(
        not(build_host_avx2),
        ignore = "the build host has no AVX2: nothing packed"
    )]
    fn packed_plate_loops_match_portable_across_the_table_and_its_border() {
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let (w, b) = (0.85f32, 0.05f32);
        let side = 10usize;
        let cells: Vec<f32> = (0..side * side)
            .map(|k| {
                let (c, r) = (k % side, k / side);
                let border = c == 0 || r == 0 || c == side - 1 || r == side - 1;
                if border || next() % 2 == 0 {
                    w
                } else {
                    b
                }
            })
            .collect();
        let rows = CellRows::new(&cells, side, w, b).expect("two albedos, 10 x 10");
        assert!(rows.pairs.is_some());
        let no_pairs = CellRows {
            pairs: None,
            ..rows
        };
        let log2 = 6;
        let lit = LitTexture {
            log2,
            data: (0..1usize << (2 * log2)).map(|_| next() as u16).collect(),
            rock_scale: 0.01,
            rock_offset: 0.2,
            caustic_scale: 0.004,
            caustic_offset: 0.5,
        };
        let caustic = PlateCaustics {
            tex: &lit,
            strength: 0.6,
            texels_per_m: 600.0,
        };
        let mut compared = 0;
        for (k, table) in [Some(&rows), Some(&no_pairs), None].into_iter().enumerate() {
            for c in [None, Some(caustic)] {
                // Rows from above the plate to below it, each from left of it to right.
                for row in 0..7 {
                    let v = -0.12 + 0.04 * row as f32;
                    let r = PlateRun {
                        d: Ramp {
                            at: 1.0,
                            step: 2e-4,
                        },
                        nu: Ramp {
                            at: -0.13,
                            step: 0.26 / 97.0,
                        },
                        nv: Ramp { at: v, step: 1e-4 },
                        half_marker: 0.06,
                        cell_per_m: (side - 2) as f32 / 0.12,
                        inv_wu: 1.0 / 0.04,
                        inv_wv: 1.0 / 0.05,
                        cells: &cells,
                        side: side as i32,
                        rows: table,
                        caustic: c,
                        ambient: Ramp {
                            at: 30.0,
                            step: 0.1,
                        },
                        lamp: Ramp {
                            at: 5.0,
                            step: -0.02,
                        },
                        add: Ramp {
                            at: 2.0,
                            step: 0.01,
                        },
                    };
                    for (first, len) in [(0usize, 97usize), (3, 40), (16, 16), (5, 7), (0, 0)] {
                        let mut want = vec![0f32; len];
                        plate_run(Isa::Portable, &mut want, first, &r);
                        for isa in [Isa::Avx2, Isa::Avx512].map(Isa::best_up_to) {
                            let mut got = vec![0f32; len];
                            plate_run(isa, &mut got, first, &r);
                            let same = got
                                .iter()
                                .zip(&want)
                                .all(|(a, b)| a.to_bits() == b.to_bits());
                            assert!(
                                same,
                                "{isa:?} table {k} caustic {} row {row} first {first}",
                                c.is_some()
                            );
                            compared += 1;
                        }
                        // Rows over the printed cells see both albedos: the comparison means something.
                        if len == 97 {
                            let (lo, hi) = want
                                .iter()
                                .fold((f32::MAX, f32::MIN), |(l, h), &m| (l.min(m), h.max(m)));
                            assert!(
                                hi > 2.0 * lo || !(2..=4).contains(&row),
                                "row {row}: {lo}..{hi}"
                            );
                        }
                    }
                }
            }
        }
        assert!(compared > 0);
    }

    #[test]
    fn cell_rows_hold_the_table_as_bits_or_decline() {
        let (w, b) = (0.85f32, 0.05f32);
        let side = 10;
        let cells: Vec<f32> = (0..side * side)
            .map(|k| if (k * 7 + k / 3) % 3 == 0 { w } else { b })
            .collect();
        let rows = CellRows::new(&cells, side, w, b).expect("a 10 x 10 table of two albedos");
        for (k, &v) in cells.iter().enumerate() {
            let bit = rows.bits[k / side] >> (k % side) & 1;
            assert_eq!(bit == 1, v == w, "cell {k}");
        }
        // Too large for two registers of eight rows, or a third value: the gathers.
        let big = vec![w; 17 * 17];
        assert!(CellRows::new(&big, 17, w, b).is_none());
        let mut odd = cells.clone();
        odd[37] = 0.5;
        assert!(CellRows::new(&odd, side, w, b).is_none());
        assert!(CellRows::new(&cells[1..], side, w, b).is_none());
    }
}
