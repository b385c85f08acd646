//! Seeded procedural textures: rock / seabed albedo and the caustic web.
//!
//! Both are square, power-of-two and tileable so that a lookup is a mask, not a modulo.

/// SplitMix64: seeds the other generators and drives start-up work.
#[derive(Debug, Clone)]
pub(crate) struct SplitMix64(u64);

impl SplitMix64 {
    pub(crate) fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub(crate) fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// A square tileable texture stored as bytes (`value = offset + scale * byte`), side
/// `1 << log2`: small enough to stay in cache while a frame renders.
#[derive(Debug, Clone, Default)]
pub(crate) struct Texture {
    pub(crate) log2: u32,
    pub(crate) data: Vec<u8>,
    pub(crate) scale: f32,
    pub(crate) offset: f32,
}

impl Texture {
    /// Quantize `values` to bytes over their range.
    fn from_values(log2: u32, values: &[f32]) -> Self {
        let lo = values.iter().cloned().fold(f32::MAX, f32::min);
        let hi = values.iter().cloned().fold(f32::MIN, f32::max);
        let scale = ((hi - lo) / 255.0).max(1e-12);
        let data = values
            .iter()
            .map(|v| ((v - lo) / scale).round().clamp(0.0, 255.0) as u8)
            .collect();
        Self {
            log2,
            data,
            scale,
            offset: lo,
        }
    }

    pub(crate) fn side(&self) -> usize {
        1 << self.log2
    }

    pub(crate) fn mask(&self) -> usize {
        self.side() - 1
    }

    /// Raw byte at texel coordinates (wraps).
    #[inline(always)]
    pub(crate) fn byte(&self, tx: i32, ty: i32) -> u8 {
        self.data[texel_index(self.log2, tx, ty)]
    }

    /// Nearest texel at texel coordinates (wraps).
    #[inline(always)]
    pub(crate) fn at(&self, tx: i32, ty: i32) -> f32 {
        self.offset + self.scale * self.byte(tx, ty) as f32
    }
}

/// Index of texel (tx, ty) in a square texture of side `1 << log2`, wrapping.
#[inline(always)]
fn texel_index(log2: u32, tx: i32, ty: i32) -> usize {
    let m = (1usize << log2) - 1;
    ((ty as usize & m) << log2) | (tx as usize & m)
}

/// Value noise lattice of side `cells` (tileable), smoothly interpolated.
fn value_noise_octave(rng: &mut SplitMix64, side: usize, cells: usize, out: &mut [f32], amp: f32) {
    let lattice: Vec<f32> = (0..cells * cells).map(|_| rng.next_f64() as f32).collect();
    let scale = cells as f32 / side as f32;
    for y in 0..side {
        let gy = y as f32 * scale;
        let iy = gy as usize;
        let fy = gy - iy as f32;
        let sy = fy * fy * (3.0 - 2.0 * fy);
        for x in 0..side {
            let gx = x as f32 * scale;
            let ix = gx as usize;
            let fx = gx - ix as f32;
            let sx = fx * fx * (3.0 - 2.0 * fx);
            let l = |i: usize, j: usize| lattice[(j % cells) * cells + (i % cells)];
            let a = l(ix, iy) + (l(ix + 1, iy) - l(ix, iy)) * sx;
            let b = l(ix, iy + 1) + (l(ix + 1, iy + 1) - l(ix, iy + 1)) * sx;
            out[y * side + x] += amp * (a + (b - a) * sy);
        }
    }
}

/// Per texel of a tileable jittered Voronoi diagram with `n` x `n` cells: the distance
/// to the nearest cell border (in cell sizes) and the nearest cell's index.
fn voronoi(rng: &mut SplitMix64, side: usize, n: usize) -> Vec<(f32, u32)> {
    let n = n.max(2);
    let cell = side as f32 / n as f32;
    let pts: Vec<(f32, f32)> = (0..n * n)
        .map(|i| {
            let (cx, cy) = ((i % n) as f32, (i / n) as f32);
            (
                (cx + 0.15 + 0.7 * rng.next_f64() as f32) * cell,
                (cy + 0.15 + 0.7 * rng.next_f64() as f32) * cell,
            )
        })
        .collect();
    let mut out = Vec::with_capacity(side * side);
    for y in 0..side {
        for x in 0..side {
            let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
            let (gx, gy) = ((px / cell) as i64, (py / cell) as i64);
            let (mut d1, mut d2, mut id) = (f32::MAX, f32::MAX, 0u32);
            for dy in -1..=1i64 {
                for dx in -1..=1i64 {
                    let (cx, cy) = (gx + dx, gy + dy);
                    let (wx, wy) = (cx.rem_euclid(n as i64), cy.rem_euclid(n as i64));
                    let k = wy as usize * n + wx as usize;
                    let (qx, qy) = pts[k];
                    // Shift the wrapped point next to this cell (tileable).
                    let qx = qx + (cx - wx) as f32 * cell;
                    let qy = qy + (cy - wy) as f32 * cell;
                    let d = ((qx - px).powi(2) + (qy - py).powi(2)).sqrt();
                    if d < d1 {
                        d2 = d1;
                        d1 = d;
                        id = k as u32;
                    } else if d < d2 {
                        d2 = d;
                    }
                }
            }
            out.push(((d2 - d1) / cell, id));
        }
    }
    out
}

/// Rock / seabed albedo: fractal value noise (stains, grain), mapped to albedo
/// `mean +- spread`. (Gravel with sharp pebble borders was tried: sampled one texel per
/// pixel it aliases at low resolutions, so the smooth noise stays.)
pub(crate) fn rock_texture(seed: u64, log2: u32, mean: f32, spread: f32) -> Texture {
    let side = 1usize << log2;
    let mut rng = SplitMix64::new(seed ^ 0x0B5E_ED00_0000_0001);
    let mut acc = vec![0f32; side * side];
    let mut amp = 1.0f32;
    let mut cells = 4usize;
    while cells <= side / 2 {
        value_noise_octave(&mut rng, side, cells, &mut acc, amp);
        amp *= 0.7;
        cells *= 2;
    }
    // Normalize to zero mean, unit range, then to albedo.
    let n = acc.len() as f32;
    let m = acc.iter().sum::<f32>() / n;
    let max_dev = acc.iter().fold(0f32, |a, v| a.max((v - m).abs())).max(1e-6);
    for v in acc.iter_mut() {
        *v = (mean + spread * (*v - m) / max_dev).clamp(0.01, 0.99);
    }
    Texture::from_values(log2, &acc)
}

/// Caustic web: bright thin lines along the borders of a jittered (tileable) Voronoi
/// diagram, the pattern refracting surface waves focus on the bottom. Two webs, one per
/// entry of `cells_per_side`, quantized on one scale (so a texel of one and a texel of
/// the other average as bytes) that gives their texels together a mean of exactly 1.
pub(crate) fn caustic_textures(seed: u64, log2: u32, cells_per_side: [usize; 2]) -> [Texture; 2] {
    let side = 1usize << log2;
    let mut rng = SplitMix64::new(seed ^ 0xCA05_71C5_0000_0002);
    // Bright near the border (distance in cell sizes).
    let mut data = Vec::with_capacity(2 * side * side);
    for cells in cells_per_side {
        data.extend(
            voronoi(&mut rng, side, cells)
                .into_iter()
                .map(|(edge, _)| (-edge * 9.0).exp()),
        );
    }
    // Bytes from 0 with a scale that makes the mean exactly 1 after quantization.
    let both = Texture::from_values(log2, &data);
    let mean_byte = both.data.iter().map(|&b| b as f64).sum::<f64>() / both.data.len() as f64;
    let scale = (1.0 / mean_byte.max(1e-6)) as f32;
    let (a, b) = both.data.split_at(side * side);
    let web = |d: &[u8]| Texture {
        log2,
        data: d.to_vec(),
        scale,
        offset: 0.0,
    };
    [web(a), web(b)]
}

impl Texture {
    /// A texture of zeros (scale 1).
    pub(crate) fn blank(log2: u32) -> Self {
        Self {
            log2,
            data: vec![0; 1 << (2 * log2)],
            scale: 1.0,
            offset: 0.0,
        }
    }
}

/// Rock albedo and caustic light on one texel grid, two bytes a texel: the rock's byte
/// (low) and the mean of the two caustic webs' bytes at this frame's drifts, rounded half
/// up (high). Built once per frame under caustics, so a pixel reads one texel for both.
#[derive(Debug, Clone, Default)]
pub(crate) struct LitTexture {
    pub(crate) log2: u32,
    pub(crate) data: Vec<u16>,
    /// `value = offset + scale * byte` of the rock and of the caustic byte.
    pub(crate) rock_scale: f32,
    pub(crate) rock_offset: f32,
    pub(crate) caustic_scale: f32,
    pub(crate) caustic_offset: f32,
}

impl LitTexture {
    /// The two bytes at texel coordinates (wraps).
    #[inline(always)]
    pub(crate) fn word(&self, tx: i32, ty: i32) -> u16 {
        self.data[texel_index(self.log2, tx, ty)]
    }

    /// Caustic value (mean 1 over the texture) at texel coordinates.
    #[inline(always)]
    pub(crate) fn caustic_at(&self, tx: i32, ty: i32) -> f32 {
        self.caustic_offset + self.caustic_scale * (self.word(tx, ty) >> 8) as f32
    }

    /// Rebuild from `rock` and the webs, web `k` moved by `shift[k]` texels: texel `p`
    /// holds `rock[p]` and `(webs[0][p + shift[0]] + webs[1][p + shift[1]] + 1) >> 1`.
    /// All three textures are the same size and both webs have the same byte scale (else
    /// the caustic bytes are left at zero). Inlined, so the renderer's AVX2 build packs
    /// 32 texels an instruction where the baseline packs 16 (byte arithmetic: the same
    /// bytes either way).
    #[inline(always)]
    pub(crate) fn build(&mut self, rock: &Texture, webs: &[Texture; 2], shift: [(i32, i32); 2]) {
        let (side, m) = (rock.side(), rock.mask());
        let n = side * side;
        self.log2 = rock.log2;
        self.rock_scale = rock.scale;
        self.rock_offset = rock.offset;
        self.caustic_scale = webs[0].scale;
        self.caustic_offset = webs[0].offset;
        self.data.resize(n, 0);
        let [a, b] = webs;
        let fits = |t: &Texture| t.log2 == rock.log2 && t.data.len() == n;
        if rock.data.len() != n {
            self.data.fill(0);
            return;
        }
        if !(fits(a) && fits(b)) || a.scale != b.scale || a.offset != b.offset {
            for (o, &r) in self.data.iter_mut().zip(&rock.data) {
                *o = r as u16;
            }
            return;
        }
        let (dxa, dxb) = (shift[0].0 as usize & m, shift[1].0 as usize & m);
        // Pieces of a row over which both webs' rows run on without wrapping.
        let mut cuts = [0, (side - dxa) & m, (side - dxb) & m, side];
        cuts.sort_unstable();
        for (y, out) in self.data.chunks_exact_mut(side).enumerate() {
            fn row(t: &Texture, y: usize, dy: i32) -> &[u8] {
                let (side, m) = (t.side(), t.mask());
                let y = (y + dy as usize) & m;
                &t.data[y * side..(y + 1) * side]
            }
            let (rr, ra, rb) = (
                row(rock, y, 0),
                row(a, y, shift[0].1),
                row(b, y, shift[1].1),
            );
            for w in cuts.windows(2) {
                let (x0, x1) = (w[0], w[1]);
                if x0 == x1 {
                    continue;
                }
                let (ia, ib) = ((x0 + dxa) & m, (x0 + dxb) & m);
                let len = x1 - x0;
                let pieces = out[x0..x1]
                    .iter_mut()
                    .zip(&rr[x0..x1])
                    .zip(ra[ia..ia + len].iter().zip(&rb[ib..ib + len]));
                for ((o, &r), (&ca, &cb)) in pieces {
                    let c = (ca as u16 + cb as u16 + 1) >> 1;
                    *o = r as u16 | c << 8;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rock_is_seeded_and_in_range() {
        let a = rock_texture(7, 6, 0.25, 0.15);
        let b = rock_texture(7, 6, 0.25, 0.15);
        let c = rock_texture(8, 6, 0.25, 0.15);
        assert_eq!(a.data, b.data);
        assert_ne!(a.data, c.data);
        let vals = |t: &Texture| -> Vec<f32> {
            (0..t.data.len())
                .map(|i| t.at((i % t.side()) as i32, (i / t.side()) as i32))
                .collect()
        };
        let v = vals(&a);
        assert!(v.iter().all(|v| (0.09..=0.41).contains(v)));
        let mean = v.iter().sum::<f32>() / v.len() as f32;
        assert!((mean - 0.25).abs() < 0.03, "{mean}");
    }

    #[test]
    fn caustics_have_unit_mean_and_contrast() {
        let webs = caustic_textures(3, 7, [6, 4]);
        assert_eq!(webs[0].scale, webs[1].scale);
        let vals = |t: &Texture| -> Vec<f32> {
            t.data
                .iter()
                .map(|&b| t.offset + t.scale * b as f32)
                .collect()
        };
        let (v0, v1) = (vals(&webs[0]), vals(&webs[1]));
        let mean = (v0.iter().sum::<f32>() + v1.iter().sum::<f32>()) / (2 * v0.len()) as f32;
        assert!((mean - 1.0).abs() < 1e-3, "{mean}");
        for v in [v0, v1] {
            let max = v.iter().cloned().fold(0f32, f32::max);
            let min = v.iter().cloned().fold(f32::MAX, f32::min);
            assert!(max > 2.0 * mean && min < 0.5 * mean, "{min} {max}");
        }
        assert_ne!(webs[0].data, webs[1].data);
    }

    #[test]
    fn caustics_tile_seamlessly() {
        // Opposite borders of a tileable texture differ no more than neighbours inside.
        let [t, _] = caustic_textures(5, 7, [5, 3]);
        let s = t.side();
        let mut border = 0f32;
        let mut inner = 0f32;
        for y in 0..s {
            let at = |x: usize| t.data[y * s + x] as f32;
            border += (at(s - 1) - at(0)).abs();
            for x in 1..s {
                inner += (at(x) - at(x - 1)).abs();
            }
        }
        // Mean jump between neighbouring columns inside.
        inner /= (s - 1) as f32;
        assert!(border < 3.0 * inner + 1e-3, "{border} vs {inner}");
    }

    #[test]
    fn lit_texture_holds_the_rock_and_the_shifted_mean_of_two_webs() {
        let rock = rock_texture(4, 5, 0.3, 0.1);
        let webs = caustic_textures(9, 5, [3, 2]);
        let mut lit = LitTexture::default();
        for shift in [[(0, 0), (0, 0)], [(7, -3), (-40, 65)], [(31, 31), (1, 30)]] {
            lit.build(&rock, &webs, shift);
            assert_eq!(lit.log2, 5);
            for (y, x) in [(0, 0), (3, 31), (31, 0), (17, 9), (30, 2)] {
                let [(ax, ay), (bx, by)] = shift;
                let want =
                    (webs[0].byte(x + ax, y + ay) as u16 + webs[1].byte(x + bx, y + by) as u16 + 1)
                        >> 1;
                let w = lit.word(x, y);
                assert_eq!(w >> 8, want, "{shift:?} at ({x}, {y})");
                assert_eq!(w & 0xFF, rock.byte(x, y) as u16);
            }
        }
    }
}
