//! The fast renderer. The scene is planar (plate, wall, seabed) so, per pixel:
//! - the ray's normalized coordinates come from a grid of undistorted rays made once
//!   (distortion folded in), interpolated linearly along 16-pixel spans;
//! - every plane's `n . r` and surface coordinates are linear forms in those coordinates,
//!   so they advance by one add per pixel, and one division gives (u, v);
//! - the light model (daylight, lamps, glare, backscatter: the exponentials) is smooth on
//!   each plane, so it is evaluated with [`Scene::shade`] only at grid nodes, lazily and
//!   per plane, and interpolated; only the albedo (marker cells, rock), the caustics and
//!   the noise are per pixel;
//! - f32 arithmetic, table lookups for noise and response, no allocation per frame.

use markhold_exposure::Frame;
use nalgebra::{Isometry3, Point3, Vector3};

use super::sensor::{SensorTables, XorShift64Star, RESPONSE_LUT_LEN};
use super::CameraModel;
use crate::scene::{
    Scene, WorldLamp, ALBEDO_BLACK, ALBEDO_WHITE, CAUSTIC_LAYER2_SCALE, CAUSTIC_LAYER2_SHIFT,
};

/// Pixels between grid nodes.
const GRID: usize = 16;
/// Surfaces with their own light fields: plate, wall, seabed, open water.
const PLATE: usize = 0;
const WALL: usize = 1;
const SEABED: usize = 2;
const WATER: usize = 3;
const NSURF: usize = 4;

/// A plane seen from the camera: `n . P = h` (h > 0) in camera coordinates, and the
/// linear forms whose ratios to `n . r` give surface coordinates.
#[derive(Debug, Clone, Copy, Default)]
struct PlaneForms {
    /// `[a, b, c]` of `a x + b y + c` for D = n . r, u numerator, v numerator.
    d: [f32; 3],
    u: [f32; 3],
    v: [f32; 3],
    h: f32,
    valid: bool,
}

/// The geometry of one plane for the frame, in f64 for shading the nodes.
#[derive(Debug, Clone, Copy)]
struct PlaneGeo {
    n_c: Vector3<f64>,
    h: f64,
    /// World normal on the side the camera sees.
    n_face_w: Vector3<f64>,
    glossy: bool,
    valid: bool,
}

impl PlaneGeo {
    /// Plane through `p0_c` with normal `n_c` and surface axes `eu_c`, `ev_c` (camera
    /// frame), `n_face_w` its world normal toward the camera.
    fn new(
        p0_c: Vector3<f64>,
        n_c: Vector3<f64>,
        eu_c: Vector3<f64>,
        ev_c: Vector3<f64>,
        n_face_w: Vector3<f64>,
        glossy: bool,
    ) -> (Self, PlaneForms) {
        let mut n = n_c;
        let mut h = n.dot(&p0_c);
        if h < 0.0 {
            n = -n;
            h = -h;
        }
        let valid = h > 1e-9;
        // u = eu . (s r - p0), s = h / (n . r)  =>  u = ((h eu - (eu . p0) n) . r) / (n . r)
        let au = eu_c * h - n * eu_c.dot(&p0_c);
        let av = ev_c * h - n * ev_c.dot(&p0_c);
        let f = |v: Vector3<f64>| [v.x as f32, v.y as f32, v.z as f32];
        (
            Self {
                n_c: n,
                h,
                n_face_w,
                glossy,
                valid,
            },
            PlaneForms {
                d: f(n),
                u: f(au),
                v: f(av),
                h: h as f32,
                valid,
            },
        )
    }
}

/// floor() without a libm call (baseline x86-64 has no rounding instruction).
#[inline(always)]
fn floor_i32(x: f32) -> i32 {
    let i = x as i32;
    i - ((i as f32) > x) as i32
}

#[inline(always)]
fn form(f: &[f32; 3], x: f32, y: f32) -> f32 {
    f[0] * x + f[1] * y + f[2]
}

/// Buffers and tables of the fast renderer, made once per camera.
pub(crate) struct FastRenderer {
    width: usize,
    height: usize,
    /// Nodes per row.
    nx: usize,
    /// Undistorted normalized coordinates of the nodes, row-major.
    node_x: Vec<f32>,
    node_y: Vec<f32>,
    /// Light fields per node and surface: ambient, lamp, additive (glare + backscatter),
    /// already in electrons for this frame's exposure.
    fields: Vec<[f32; 3]>,
    /// Frame id for which `fields[i]` is valid.
    stamp: Vec<u32>,
    frame_id: u32,
    /// Row-interpolated node coordinates of the current row.
    row_x: Vec<f32>,
    row_y: Vec<f32>,
    /// Mean electrons of the current row's pixels (the sensor runs as a second pass).
    row_mean: Vec<f32>,
    /// Half Gaussian samples and response-table indices of the current row.
    row_g: Vec<f32>,
    row_idx: Vec<u32>,
}

/// Everything the per-pixel loop needs for one frame.
struct FrameCtx<'a> {
    scene: &'a Scene,
    t_wc: &'a Isometry3<f64>,
    lamps: &'a [WorldLamp],
    geo: [PlaneGeo; 3],
    forms: [PlaneForms; 3],
    e_per_unit: f64,
}

impl FastRenderer {
    pub(crate) fn new(model: &CameraModel) -> Self {
        let (w, h) = (model.width as usize, model.height as usize);
        let nx = (w - 1) / GRID + 2;
        let ny = (h - 1) / GRID + 2;
        let mut node_x = Vec::with_capacity(nx * ny);
        let mut node_y = Vec::with_capacity(nx * ny);
        for j in 0..ny {
            for i in 0..nx {
                let (x, y) = model.undistort_pixel((i * GRID) as f64, (j * GRID) as f64);
                node_x.push(x as f32);
                node_y.push(y as f32);
            }
        }
        Self {
            width: w,
            height: h,
            nx,
            node_x,
            node_y,
            fields: vec![[0.0; 3]; nx * ny * NSURF],
            stamp: vec![u32::MAX; nx * ny * NSURF],
            frame_id: 0,
            row_x: vec![0.0; nx],
            row_y: vec![0.0; nx],
            row_mean: vec![0.0; w],
            row_g: vec![0.0; w],
            row_idx: vec![0; w],
        }
    }

    /// The light fields of `surf` at node `node`, computed on first use this frame.
    #[inline]
    fn node_fields(&mut self, ctx: &FrameCtx, node: usize, surf: usize) -> [f32; 3] {
        let idx = node * NSURF + surf;
        if self.stamp[idx] == self.frame_id {
            return self.fields[idx];
        }
        let x = self.node_x[node] as f64;
        let y = self.node_y[node] as f64;
        let r_c = Vector3::new(x, y, 1.0);
        let norm = r_c.norm();
        let ray_w = ctx.t_wc.rotation * (r_c / norm);
        let cam_w = ctx.t_wc.translation.vector;
        let scene = ctx.scene;
        let f = if surf == WATER {
            let b = scene.backscatter(&cam_w, &ray_w, f64::INFINITY, ctx.lamps);
            [0.0, 0.0, b]
        } else {
            let g = &ctx.geo[surf];
            let d = g.n_c.dot(&r_c);
            if !g.valid || d <= 1e-9 {
                // Never reached along this ray: the limit at infinite distance.
                let b = scene.backscatter(&cam_w, &ray_w, f64::INFINITY, ctx.lamps);
                [0.0, 0.0, b]
            } else {
                let s = g.h / d;
                let p_w = (ctx.t_wc * Point3::from(r_c * s)).coords;
                let sh = scene.shade(
                    &p_w,
                    &g.n_face_w,
                    &cam_w,
                    &ray_w,
                    s * norm,
                    ctx.lamps,
                    g.glossy,
                );
                [sh.ambient, sh.lamp, sh.glare + sh.backscatter]
            }
        };
        let k = ctx.e_per_unit;
        let f = [(f[0] * k) as f32, (f[1] * k) as f32, (f[2] * k) as f32];
        self.fields[idx] = f;
        self.stamp[idx] = self.frame_id;
        f
    }

    /// Fields of `surf` at the left end of span `i` of row-cell `j` (vertical weight
    /// `fy`) and their step per pixel.
    #[inline]
    fn span_fields(
        &mut self,
        ctx: &FrameCtx,
        i: usize,
        j: usize,
        fy: f32,
        surf: usize,
    ) -> ([f32; 3], [f32; 3]) {
        let n00 = self.node_fields(ctx, j * self.nx + i, surf);
        let n10 = self.node_fields(ctx, j * self.nx + i + 1, surf);
        let n01 = self.node_fields(ctx, (j + 1) * self.nx + i, surf);
        let n11 = self.node_fields(ctx, (j + 1) * self.nx + i + 1, surf);
        let mut f0 = [0f32; 3];
        let mut df = [0f32; 3];
        for c in 0..3 {
            let l = n00[c] + (n01[c] - n00[c]) * fy;
            let r = n10[c] + (n11[c] - n10[c]) * fy;
            f0[c] = l;
            df[c] = (r - l) * (1.0 / GRID as f32);
        }
        (f0, df)
    }

    #[allow(clippy::too_many_arguments)]
    pub(crate) fn render(
        &mut self,
        model: &CameraModel,
        scene: &Scene,
        t_wc: &Isometry3<f64>,
        lamps: &[WorldLamp],
        time_s: f64,
        e_per_unit: f64,
        tables: &SensorTables,
        rng: &mut XorShift64Star,
        out: &mut Frame,
    ) {
        self.frame_id = self.frame_id.wrapping_add(1);
        if self.frame_id == u32::MAX {
            self.stamp.fill(u32::MAX - 1);
            self.frame_id = 0;
        }
        let (geo, forms) = frame_planes(scene, t_wc);
        let ctx = FrameCtx {
            scene,
            t_wc,
            lamps,
            geo,
            forms,
            e_per_unit,
        };
        let plate_front = geo[PLATE].glossy;
        let footprint = plate_footprint(model, scene, t_wc, &forms[PLATE]);

        // Per-frame constants of the per-pixel work, in f32.
        let m = scene.marker();
        let half = scene.plate_half_m() as f32;
        let cells = m.cells;
        let cell_per_m = cells as f32 / m.size_m as f32;
        let half_marker = 0.5 * m.size_m as f32;
        // Footprint in cells: the width of the box filter over the cell grid.
        let inv_wu = 1.0 / (footprint.0 as f32 * cell_per_m).max(1e-6);
        let inv_wv = 1.0 / (footprint.1 as f32 * cell_per_m).max(1e-6);
        let albedo_white = ALBEDO_WHITE as f32;
        let albedo_black = ALBEDO_BLACK as f32;
        let albedo_back = scene.plate_back_albedo() as f32;
        let texel_per_m = (1.0 / scene.background.texel_m) as f32;
        let rock = &scene.rock;
        let caustics = CausticFrame::new(scene, time_s);
        let gauss = &tables.half_gauss;
        let gmask = tables.gauss_mask();
        let lut: &[u8; RESPONSE_LUT_LEN] = &tables.response_lut;
        let lut_top = (lut.len() - 1) as f32;
        if !tables.noise {
            self.row_g.fill(0.0);
        }

        let (w, h, nx) = (self.width, self.height, self.nx);
        let cell_albedo = |ci: i32, cj: i32| -> f32 {
            // Outside the printed square is the white plate.
            let outside = ci < 0 || cj < 0 || ci >= cells as i32 || cj >= cells as i32;
            if outside || m.white[cj as usize * cells + ci as usize] {
                albedo_white
            } else {
                albedo_black
            }
        };

        for (py, row) in out.data.chunks_exact_mut(w).enumerate().take(h) {
            let j = py / GRID;
            let fy = (py - j * GRID) as f32 * (1.0 / GRID as f32);
            for i in 0..nx {
                let a = j * nx + i;
                let b = a + nx;
                self.row_x[i] = self.node_x[a] + (self.node_x[b] - self.node_x[a]) * fy;
                self.row_y[i] = self.node_y[a] + (self.node_y[b] - self.node_y[a]) * fy;
            }
            let mut row_mean = std::mem::take(&mut self.row_mean);
            for i in 0..nx - 1 {
                let x0 = i * GRID;
                if x0 >= w {
                    break;
                }
                let x1 = (x0 + GRID).min(w);
                let n = x1 - x0;
                let (xa, ya) = (self.row_x[i], self.row_y[i]);
                let (xb, yb) = (self.row_x[i + 1], self.row_y[i + 1]);
                // Linear forms of every plane at the span start and their step per pixel.
                let mut sp = Span::default();
                for k in 0..3 {
                    let fm = &ctx.forms[k];
                    for (c, coef) in [&fm.d, &fm.u, &fm.v].into_iter().enumerate() {
                        let s = form(coef, xa, ya);
                        sp.f0[k][c] = s;
                        sp.df[k][c] = (form(coef, xb, yb) - s) * (1.0 / GRID as f32);
                    }
                }
                // Every test that picks the surface is the sign of a linear function of
                // the pixel (u = Nu / D is monotonic while D > 0): between their roots
                // the surface is the same, so the span splits into runs of one surface.
                let mut cuts = Cuts::new(n);
                let (p0, pd) = (sp.f0[PLATE], sp.df[PLATE]);
                cuts.root(p0[0], pd[0]);
                for c in 1..3 {
                    cuts.root(p0[c] - half * p0[0], pd[c] - half * pd[0]);
                    cuts.root(p0[c] + half * p0[0], pd[c] + half * pd[0]);
                }
                cuts.root(sp.f0[WALL][0], sp.df[WALL][0]);
                cuts.root(sp.f0[SEABED][0], sp.df[SEABED][0]);
                let (hw, hs) = (ctx.forms[WALL].h, ctx.forms[SEABED].h);
                cuts.root(
                    hw * sp.f0[SEABED][0] - hs * sp.f0[WALL][0],
                    hw * sp.df[SEABED][0] - hs * sp.df[WALL][0],
                );
                cuts.sort(n);
                let mut ready = [false; NSURF];
                let mut lf = [([0f32; 3], [0f32; 3]); NSURF];
                let out = &mut row_mean[x0..x1];
                let mut start = 0usize;
                for c in 0..=cuts.n {
                    let end = if c < cuts.n { cuts.at[c] } else { n };
                    if end <= start {
                        continue;
                    }
                    let surf = classify(&sp, &ctx.forms, half, ((start + end - 1) / 2) as f32);
                    if !ready[surf] {
                        lf[surf] = self.span_fields(&ctx, i, j, fy, surf);
                        ready[surf] = true;
                    }
                    let (a0, ad) = lf[surf];
                    let run = &mut out[start..end];
                    let first = start as f32;
                    match surf {
                        WATER => {
                            for (t, m) in run.iter_mut().enumerate() {
                                *m = a0[2] + ad[2] * (first + t as f32);
                            }
                        }
                        PLATE if plate_front => {
                            let (d0, dd) = (p0[0], pd[0]);
                            for (t, m) in run.iter_mut().enumerate() {
                                let t = first + t as f32;
                                let inv = 1.0 / (d0 + dd * t);
                                let u = (p0[1] + pd[1] * t) * inv;
                                let v = (p0[2] + pd[2] * t) * inv;
                                // Box filter of the cells over the pixel footprint.
                                let cu = (u + half_marker) * cell_per_m;
                                let cv = (half_marker - v) * cell_per_m;
                                let (iu, iv) = (floor_i32(cu + 0.5), floor_i32(cv + 0.5));
                                let au = ((iu as f32 - cu) * inv_wu + 0.5).clamp(0.0, 1.0);
                                let av = ((iv as f32 - cv) * inv_wv + 0.5).clamp(0.0, 1.0);
                                let albedo = au
                                    * (av * cell_albedo(iu - 1, iv - 1)
                                        + (1.0 - av) * cell_albedo(iu - 1, iv))
                                    + (1.0 - au)
                                        * (av * cell_albedo(iu, iv - 1)
                                            + (1.0 - av) * cell_albedo(iu, iv));
                                let c = if caustics.on {
                                    caustics.at(scene, u, v)
                                } else {
                                    1.0
                                };
                                *m = albedo * ((a0[0] + ad[0] * t) * c + a0[1] + ad[1] * t)
                                    + a0[2]
                                    + ad[2] * t;
                            }
                        }
                        PLATE => {
                            for (t, m) in run.iter_mut().enumerate() {
                                let t = first + t as f32;
                                *m = albedo_back * (a0[0] + ad[0] * t + a0[1] + ad[1] * t)
                                    + a0[2]
                                    + ad[2] * t;
                            }
                        }
                        k => {
                            let (f0, fd) = (sp.f0[k], sp.df[k]);
                            // Surface coordinates are affine along a 16-pixel span to well
                            // under a texel (the division would cost more than the rest):
                            // exact at both ends, stepped in 16.16 fixed point.
                            let d_end = f0[0] + fd[0] * GRID as f32;
                            let affine = (f0[0] > 1e-6 && d_end > 1e-6).then(|| {
                                let (u0, v0) = (f0[1] / f0[0], f0[2] / f0[0]);
                                let u1 = (f0[1] + fd[1] * GRID as f32) / d_end;
                                let v1 = (f0[2] + fd[2] * GRID as f32) / d_end;
                                let g = 1.0 / GRID as f32;
                                (u0, (u1 - u0) * g, v0, (v1 - v0) * g)
                            });
                            let mut fields = Stepper::new(a0, ad, first);
                            match affine.and_then(|(u0, du, v0, dv)| {
                                RockSteps::new(u0, du, v0, dv, first, texel_per_m, &caustics)
                            }) {
                                Some(mut st) if !caustics.on => {
                                    // Daylight and lamps add up before the albedo.
                                    let (l, ld) =
                                        (fields.v[0] + fields.v[1], fields.d[0] + fields.d[1]);
                                    let (a, ad) = (fields.v[2], fields.d[2]);
                                    // albedo = offset + scale * byte: fold both into the
                                    // light terms so a pixel is one multiply-add.
                                    let (ts, to) = (rock.scale, rock.offset);
                                    let (mut ls, lds) = (l * ts, ld * ts);
                                    let (mut ao, aod) = (a + l * to, ad + ld * to);
                                    let (tex, mask, shift) =
                                        (&rock.data[..], rock.mask(), rock.log2);
                                    for m in run.iter_mut() {
                                        let tx = (st.ru.at >> 16) as usize & mask;
                                        let ty = (st.rv.at >> 16) as usize & mask;
                                        let b = tex.get((ty << shift) | tx).copied().unwrap_or(0);
                                        *m = b as f32 * ls + ao;
                                        st.step_rock();
                                        ls += lds;
                                        ao += aod;
                                    }
                                }
                                Some(mut st) => {
                                    let ct = &scene.caustic;
                                    for m in run.iter_mut() {
                                        let albedo = rock.at(st.ru.get(), st.rv.get());
                                        let c = caustics.combine(
                                            ct.at(st.c0u.get(), st.c0v.get()),
                                            ct.at(st.c1u.get(), st.c1v.get()),
                                        );
                                        *m = albedo * (fields.v[0] * c + fields.v[1]) + fields.v[2];
                                        st.step();
                                        fields.step();
                                    }
                                }
                                None => {
                                    // Near the horizon: exact per pixel.
                                    for (t, m) in run.iter_mut().enumerate() {
                                        let t = first + t as f32;
                                        let inv = 1.0 / (f0[0] + fd[0] * t);
                                        let u = (f0[1] + fd[1] * t) * inv;
                                        let v = (f0[2] + fd[2] * t) * inv;
                                        let tk = texel_per_m;
                                        let albedo = rock.at(floor_i32(u * tk), floor_i32(v * tk));
                                        let c = if caustics.on {
                                            caustics.at(scene, u, v)
                                        } else {
                                            1.0
                                        };
                                        *m = albedo * (fields.v[0] * c + fields.v[1]) + fields.v[2];
                                        fields.step();
                                    }
                                }
                            }
                        }
                    }
                    start = end;
                }
            }
            // The sensor, in three passes so the arithmetic one vectorizes.
            if tables.noise {
                // Four 16-bit picks per 64-bit draw.
                for quad in self.row_g.chunks_mut(4) {
                    let mut bits = rng.next_u64();
                    for g in quad {
                        *g = gauss[(bits as usize) & gmask];
                        bits >>= 16;
                    }
                }
            }
            let (r2, per_s, top) = (tables.read_var_e2, tables.lut_per_s, lut_top);
            // Float only, so it runs on packed registers: the square root, then the table
            // index made an integer by the 2^23 trick (adding 2^23 to a float in
            // [0, 2^23) leaves the rounded integer in its mantissa bits).
            for ((ix, &m), &g) in self.row_idx.iter_mut().zip(&row_mean).zip(&self.row_g) {
                let s = (m.max(0.0) + r2).sqrt() + g;
                *ix = ((s * per_s).clamp(0.0, top) + 8_388_608.0).to_bits() & 0x7F_FFFF;
            }
            for (px, &ix) in row.iter_mut().zip(&self.row_idx) {
                *px = lut[ix as usize & (RESPONSE_LUT_LEN - 1)];
            }
            self.row_mean = row_mean;
        }
    }
}

/// The linear forms (D, Nu, Nv) of the three planes along one span: value at the span
/// start and step per pixel.
#[derive(Debug, Clone, Copy, Default)]
struct Span {
    f0: [[f32; 3]; 3],
    df: [[f32; 3]; 3],
}

/// Pixel offsets in a span where a surface test changes sign, sorted.
#[derive(Debug, Default)]
struct Cuts {
    raw: [f32; 8],
    at: [usize; 8],
    n: usize,
    /// Offset of the span's last pixel.
    last: f32,
}

impl Cuts {
    fn new(len: usize) -> Self {
        Self {
            last: len as f32 - 1.0,
            ..Self::default()
        }
    }

    /// The root of `a + b t`, when the sign changes between the span's first and last
    /// pixels (most spans see no change: no division, one run).
    #[inline(always)]
    fn root(&mut self, a: f32, b: f32) {
        let e = a + b * self.last;
        if (a > 0.0) != (e > 0.0) && self.n < self.raw.len() {
            self.raw[self.n] = -a / b;
            self.n += 1;
        }
    }

    /// Sort and turn into the first pixel of each new run (pixel t lies past root r
    /// when t > r).
    #[inline]
    fn sort(&mut self, len: usize) {
        let raw = &mut self.raw[..self.n];
        // Insertion sort: a handful of values at most.
        for k in 1..raw.len() {
            let mut m = k;
            while m > 0 && raw[m - 1] > raw[m] {
                raw.swap(m - 1, m);
                m -= 1;
            }
        }
        for (a, r) in self.at.iter_mut().zip(raw.iter()) {
            *a = ((floor_i32(*r) + 1).max(0) as usize).min(len);
        }
    }
}

/// The surface pixel `t` of a span sees (the per-pixel test the runs stand for).
#[inline]
fn classify(sp: &Span, forms: &[PlaneForms; 3], half: f32, t: f32) -> usize {
    let at = |k: usize, c: usize| sp.f0[k][c] + sp.df[k][c] * t;
    // Plate first: it stands in front of the wall.
    let dp = at(PLATE, 0);
    if forms[PLATE].valid && dp > 1e-9 {
        let (nu, nv) = (at(PLATE, 1), at(PLATE, 2));
        if nu.abs() <= half * dp && nv.abs() <= half * dp {
            return PLATE;
        }
    }
    let dw = at(WALL, 0);
    let ds = at(SEABED, 0);
    let wall_ok = forms[WALL].valid && dw > 1e-9;
    let sea_ok = forms[SEABED].valid && ds > 1e-9;
    // The nearer plane: h_w / dw < h_s / ds.
    if wall_ok && (!sea_ok || forms[WALL].h * ds < forms[SEABED].h * dw) {
        WALL
    } else if sea_ok {
        SEABED
    } else {
        WATER
    }
}

/// Caustic lookups for one frame (same model as [`Scene::caustic`], in f32).
struct CausticFrame {
    on: bool,
    strength: f32,
    texels_per_m: f32,
    off0: (f32, f32),
    off1: (f32, f32),
}

impl CausticFrame {
    fn new(scene: &Scene, t: f64) -> Self {
        let p = scene.caustic_params(t);
        Self {
            on: p.strength > 0.0,
            strength: p.strength as f32,
            texels_per_m: p.texels_per_m as f32,
            off0: (p.off0.0 as f32, p.off0.1 as f32),
            off1: (p.off1.0 as f32, p.off1.1 as f32),
        }
    }

    /// Caustic factor at surface coordinates (u, v), metres.
    #[inline(always)]
    fn at(&self, scene: &Scene, u: f32, v: f32) -> f32 {
        let k = self.texels_per_m;
        let (s2, sh) = (CAUSTIC_LAYER2_SCALE, CAUSTIC_LAYER2_SHIFT);
        let t = &scene.caustic;
        self.combine(
            t.at(
                floor_i32((u + self.off0.0) * k),
                floor_i32((v + self.off0.1) * k),
            ),
            t.at(
                floor_i32((u * s2 + self.off1.0) * k + sh.0),
                floor_i32((v * s2 + self.off1.1) * k + sh.1),
            ),
        )
    }

    #[inline(always)]
    fn combine(&self, l0: f32, l1: f32) -> f32 {
        1.0 + self.strength * (0.5 * (l0 + l1) - 1.0)
    }
}

/// A texel coordinate stepped along a run in 16.16 fixed point.
#[derive(Debug, Clone, Copy)]
struct Fixed {
    at: i64,
    step: i64,
}

impl Fixed {
    /// `start + step * t` texels; `None` when out of the exactly representable range.
    fn new(start: f32, step: f32) -> Option<Self> {
        let ok = start.is_finite() && step.is_finite() && start.abs() < 1e9 && step.abs() < 1e7;
        ok.then(|| {
            let at = start as f64 * 65536.0;
            // floor() without a libm call; the step's truncation errs by 2^-16 texel.
            let i = at as i64;
            Self {
                at: i - ((i as f64) > at) as i64,
                step: (step as f64 * 65536.0) as i64,
            }
        })
    }

    #[inline(always)]
    fn get(&self) -> i32 {
        // Arithmetic shift: floor for negative coordinates too.
        (self.at >> 16) as i32
    }
}

/// The texel coordinates a rock run walks: the rock itself and both caustic layers.
struct RockSteps {
    ru: Fixed,
    rv: Fixed,
    c0u: Fixed,
    c0v: Fixed,
    c1u: Fixed,
    c1v: Fixed,
}

impl RockSteps {
    /// From affine surface coordinates `u0 + du t`, `v0 + dv t` (metres), at pixel `first`.
    /// The caustic layers are stepped only when caustics are on.
    fn new(
        u0: f32,
        du: f32,
        v0: f32,
        dv: f32,
        first: f32,
        rock_per_m: f32,
        c: &CausticFrame,
    ) -> Option<Self> {
        let (u, v) = (u0 + du * first, v0 + dv * first);
        let k = c.texels_per_m;
        let (s2, sh) = (CAUSTIC_LAYER2_SCALE, CAUSTIC_LAYER2_SHIFT);
        let none = Fixed { at: 0, step: 0 };
        let caustic = if c.on {
            [
                Fixed::new((u + c.off0.0) * k, du * k)?,
                Fixed::new((v + c.off0.1) * k, dv * k)?,
                Fixed::new((u * s2 + c.off1.0) * k + sh.0, du * s2 * k)?,
                Fixed::new((v * s2 + c.off1.1) * k + sh.1, dv * s2 * k)?,
            ]
        } else {
            [none; 4]
        };
        Some(Self {
            ru: Fixed::new(u * rock_per_m, du * rock_per_m)?,
            rv: Fixed::new(v * rock_per_m, dv * rock_per_m)?,
            c0u: caustic[0],
            c0v: caustic[1],
            c1u: caustic[2],
            c1v: caustic[3],
        })
    }

    #[inline(always)]
    fn step_rock(&mut self) {
        self.ru.at += self.ru.step;
        self.rv.at += self.rv.step;
    }

    #[inline(always)]
    fn step(&mut self) {
        self.step_rock();
        self.c0u.at += self.c0u.step;
        self.c0v.at += self.c0v.step;
        self.c1u.at += self.c1u.step;
        self.c1v.at += self.c1v.step;
    }
}

/// Light fields stepped along a run.
struct Stepper {
    v: [f32; 3],
    d: [f32; 3],
}

impl Stepper {
    fn new(a0: [f32; 3], ad: [f32; 3], first: f32) -> Self {
        Self {
            v: [
                a0[0] + ad[0] * first,
                a0[1] + ad[1] * first,
                a0[2] + ad[2] * first,
            ],
            d: ad,
        }
    }

    #[inline(always)]
    fn step(&mut self) {
        for c in 0..3 {
            self.v[c] += self.d[c];
        }
    }
}

/// The three planes in the camera frame for this frame.
fn frame_planes(scene: &Scene, t_wc: &Isometry3<f64>) -> ([PlaneGeo; 3], [PlaneForms; 3]) {
    let t_cw = t_wc.inverse();
    let t_wm = scene.t_world_marker();
    let t_cm = t_cw * t_wm;
    let xm = t_cm.rotation * Vector3::x();
    let ym = t_cm.rotation * Vector3::y();
    let zm = t_cm.rotation * Vector3::z();
    let om = t_cm.translation.vector;
    let nm_w = t_wm.rotation * Vector3::z();
    let cam_w = t_wc.translation.vector;
    let om_w = t_wm.translation.vector;
    let bg = &scene.background;

    let front = nm_w.dot(&(cam_w - om_w)) > 0.0;
    let plate = PlaneGeo::new(om, zm, xm, ym, if front { nm_w } else { -nm_w }, front);

    let wall_w = om_w - nm_w * bg.wall_behind_marker_m;
    let wall_front = nm_w.dot(&(cam_w - wall_w)) > 0.0;
    let wall = PlaneGeo::new(
        om - zm * bg.wall_behind_marker_m,
        zm,
        xm,
        ym,
        if wall_front { nm_w } else { -nm_w },
        false,
    );

    let seabed_z = om_w.z + bg.seabed_below_marker_m;
    let p0 = t_cw * Point3::new(0.0, 0.0, seabed_z);
    let up_w = Vector3::new(0.0, 0.0, -1.0);
    let seabed = PlaneGeo::new(
        p0.coords,
        t_cw.rotation * Vector3::z(),
        t_cw.rotation * Vector3::x(),
        t_cw.rotation * Vector3::y(),
        if cam_w.z < seabed_z { up_w } else { -up_w },
        false,
    );
    ([plate.0, wall.0, seabed.0], [plate.1, wall.1, seabed.1])
}

/// Width and height (metres, marker frame) of one pixel's footprint on the plate near
/// its centre: the bounding box of the pixel's image on the plate.
fn plate_footprint(
    model: &CameraModel,
    scene: &Scene,
    t_wc: &Isometry3<f64>,
    forms: &PlaneForms,
) -> (f64, f64) {
    let p_c = t_wc.inverse_transform_point(&scene.t_world_marker().translation.vector.into());
    let Some(px) = model.project(&p_c) else {
        return (1e-6, 1e-6);
    };
    let uv = |du: f64, dv: f64| -> Option<(f64, f64)> {
        let (x, y) = model.undistort_pixel(px[0] + du, px[1] + dv);
        let d = form(&forms.d, x as f32, y as f32) as f64;
        if d <= 1e-9 {
            return None;
        }
        Some((
            form(&forms.u, x as f32, y as f32) as f64 / d,
            form(&forms.v, x as f32, y as f32) as f64 / d,
        ))
    };
    match (uv(0.0, 0.0), uv(1.0, 0.0), uv(0.0, 1.0)) {
        (Some(a), Some(b), Some(c)) => (
            (b.0 - a.0).abs() + (c.0 - a.0).abs(),
            (b.1 - a.1).abs() + (c.1 - a.1).abs(),
        ),
        _ => (1e-6, 1e-6),
    }
}
