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

mod map;

use markhold_exposure::Frame;
use nalgebra::{Isometry3, Point3, Vector3};

use super::kernels::{
    fold_rock_cell, plate_run, ramp_run, rock_nodes_run, sensor_run, top_and_change, CellRows, Isa,
    PlateCaustics, PlateRun, Ramp, RockFold, RockNodes, SensorRow,
};
use super::sensor::{SensorTables, XorShift64Star, RESPONSE_LUT_LEN};
use super::{CameraModel, FrameInput, RenderLoops};
use crate::scene::{LitTexture, MarkerSpec, Scene, WorldLamp, ALBEDO_BLACK, ALBEDO_WHITE};

/// Pixels between grid nodes.
const GRID: usize = 16;
/// Relative and absolute (electrons) agreement of two light nodes 32 pixels apart under
/// which the node between them is interpolated where the nodes 96 pixels apart are
/// beyond the grid (at the image border).
const LIGHT_REL_TOL: f32 = 0.02;
const LIGHT_ABS_TOL_E: f32 = 0.5;
/// Elsewhere: the estimated error of interpolating, relative to the light and in
/// electrons, under which the node is interpolated instead of shaded.
const LIGHT_CURVE_TOL: f32 = 0.0025;
const LIGHT_CURVE_ABS_E: f32 = 0.05;
/// The adaptive light grid's shaded base grid, nodes apart: 64 pixels where every lamp's
/// light changes over at least `LIGHT_CELLS_PER_FEATURE` such cells in the picture,
/// else 32 (a narrow lamp's spot, or a short focal length).
const LIGHT_BASE_WIDE: usize = 4;
const LIGHT_BASE_NARROW: usize = 2;
const LIGHT_CELLS_PER_FEATURE: f64 = 4.0;
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
    /// The planes' forms (laid out like `row_forms`) on the current cell row's top grid
    /// row, then their change to the bottom one: a row's forms are a lerp of the two
    /// (the forms are affine in the ray, the ray is lerped between grid rows).
    cell_forms: Vec<f32>,
    /// The current row at its nodes: the planes' forms `(k * 3 + c) * nx + i`, the signs
    /// of the surface tests, the rock planes' texel walks and whether they are affine.
    row_forms: Vec<f32>,
    row_mask: Vec<u8>,
    row_mask32: Vec<u32>,
    row_walks: Vec<i32>,
    row_affine: Vec<bool>,
    /// Light fields of the current row at its nodes, per surface (`surf * nx + i`),
    /// computed on first use in the row.
    /// Light fields per surface and node of the current cell row (between grid rows
    /// `j` and `j + 1`): the top node's three fields and the bottom minus the top
    /// (`surf * nx + i`), valid where `cell_stamp` equals `cell_id`; `cell_range` is a
    /// node range per surface known to be valid (skips the stamp checks).
    cell_fields: Vec<[f32; 6]>,
    cell_stamp: Vec<u32>,
    cell_id: u32,
    cell_range: [(usize, usize); NSURF],
    /// The rock planes' cell fields folded for the rock loops (`fold_rock_cell`;
    /// `p * nx + i`, p = surface - WALL), valid with `cell_fields`.
    rock_cells: Vec<[f32; 6]>,
    /// Mean electrons of the current row's pixels (the sensor runs as a second pass).
    row_mean: Vec<f32>,
    /// A row of zero noise (noise off).
    zero_noise: Vec<i16>,
    /// The marker's cell albedos for `PlateRun`, refilled per frame.
    cell_table: Vec<f32>,
    /// The frame's rock-and-caustic texture (`LitTexture::build`): under caustics a
    /// rock pixel reads one texel for its albedo and its caustic light.
    lit: LitTexture,
    /// The map's other plates, placed per frame.
    map: map::MapPlates,
    isa: Isa,
}

/// Texel walks per rock plane and node: rock u, v (the caustic webs lie on the same
/// texel grid).
const WALKS: usize = 2;

/// Everything the per-pixel loop needs for one frame.
struct FrameCtx<'a> {
    scene: &'a Scene,
    t_wc: &'a Isometry3<f64>,
    lamps: &'a [WorldLamp],
    geo: [PlaneGeo; 3],
    forms: [PlaneForms; 3],
    e_per_unit: f64,
    /// Nodes between the adaptive light grid's shaded nodes (see `light_base`).
    light_base: usize,
    /// How the rock planes' fields fold into the rock loops this frame.
    rock_fold: RockFold,
}

impl FrameCtx<'_> {
    /// Light fields (electrons) of open water along normalized ray (x, y).
    fn shade_water(&self, x: f32, y: f32) -> [f32; 3] {
        let r_c = Vector3::new(x as f64, y as f64, 1.0);
        let ray_w = self.t_wc.rotation * (r_c / r_c.norm());
        let cam_w = self.t_wc.translation.vector;
        let b = self
            .scene
            .backscatter(&cam_w, &ray_w, f64::INFINITY, self.lamps);
        [0.0, 0.0, (b * self.e_per_unit) as f32]
    }

    /// Light fields (electrons) of plane `g` where normalized ray (x, y) meets it (its
    /// limit at infinite distance where the ray never does).
    fn shade_on(&self, g: &PlaneGeo, x: f32, y: f32) -> [f32; 3] {
        let r_c = Vector3::new(x as f64, y as f64, 1.0);
        let norm = r_c.norm();
        let ray_w = self.t_wc.rotation * (r_c / norm);
        let cam_w = self.t_wc.translation.vector;
        let scene = self.scene;
        let d = g.n_c.dot(&r_c);
        let f = if !g.valid || d <= 1e-9 {
            let b = scene.backscatter(&cam_w, &ray_w, f64::INFINITY, self.lamps);
            [0.0, 0.0, b]
        } else {
            let s = g.h / d;
            let p_w = (self.t_wc * Point3::from(r_c * s)).coords;
            let sh = scene.shade(
                &p_w,
                &g.n_face_w,
                &cam_w,
                &ray_w,
                s * norm,
                self.lamps,
                g.glossy,
            );
            [sh.ambient, sh.lamp, sh.glare + sh.backscatter]
        };
        let k = self.e_per_unit;
        [(f[0] * k) as f32, (f[1] * k) as f32, (f[2] * k) as f32]
    }
}

/// The adaptive light grid's base spacing (nodes) for this frame. The narrowest thing
/// in the light is a lamp's cone edge (or its inner cone), `min(outer - inner, inner)`
/// wide as seen from the lamp; seen from the camera it shrinks by the ratio of the
/// lamp's and the camera's distances to the marker's plane (a lamp on the vehicle: about
/// 1; the marker's own lamp: much less). Daylight and backscatter change slowly.
fn light_base(
    model: &CameraModel,
    scene: &Scene,
    t_wc: &Isometry3<f64>,
    lamps: &[WorldLamp],
) -> usize {
    let t_wm = scene.t_world_marker();
    let (o, n) = (t_wm.translation.vector, t_wm.rotation * Vector3::z());
    let plane_dist = |p: &Vector3<f64>| n.dot(&(p - o)).abs().max(0.1);
    let d_cam = plane_dist(&t_wc.translation.vector);
    let feature_rad = lamps.iter().fold(f64::INFINITY, |m, l| {
        let (inner, outer) = (
            l.cos_inner.clamp(-1.0, 1.0).acos(),
            l.cos_outer.clamp(-1.0, 1.0).acos(),
        );
        m.min((outer - inner).min(inner) * (plane_dist(&l.pos) / d_cam).min(1.0))
    });
    let wide_cell_rad = (LIGHT_BASE_WIDE * GRID) as f64 / model.fx.min(model.fy);
    if feature_rad >= LIGHT_CELLS_PER_FEATURE * wide_cell_rad {
        LIGHT_BASE_WIDE
    } else {
        LIGHT_BASE_NARROW
    }
}

/// Per-frame constants of the per-pixel work, in f32.
struct PixelConsts<'a> {
    scene: &'a Scene,
    plate_front: bool,
    half: f32,
    cells: usize,
    /// Cell albedos with a one-cell white border (see `PlateRun`).
    cell_table: &'a [f32],
    /// The same as bits, where they fit.
    cell_rows: Option<CellRows>,
    cell_per_m: f32,
    half_marker: f32,
    inv_wu: f32,
    inv_wv: f32,
    albedo_back: f32,
    texel_per_m: f32,
    caustics: CausticFrame,
    /// The frame's rock-and-caustic texture (meaningful when `caustics.on`).
    lit: &'a LitTexture,
    plate_caustics: Option<PlateCaustics<'a>>,
    isa: Isa,
}

impl<'a> PixelConsts<'a> {
    /// The frame's constants: the marker's cell grid and its box filter, the plate, the
    /// rock's texel scale and the caustics.
    #[inline(always)]
    fn new(
        model: &CameraModel,
        ctx: &FrameCtx<'a>,
        caustics: CausticFrame,
        lit: &'a LitTexture,
        cell_table: &'a [f32],
        isa: Isa,
    ) -> Self {
        let scene = ctx.scene;
        let footprint = plate_footprint(model, ctx.t_wc, scene.t_world_marker(), &ctx.forms[PLATE]);
        let m = scene.marker();
        let cell_per_m = m.cells as f32 / m.size_m as f32;
        let side = m.cells + 2;
        let texel_per_m = (1.0 / scene.background.texel_m) as f32;
        let plate_caustics = caustics.on.then_some(PlateCaustics {
            tex: lit,
            strength: caustics.strength,
            texels_per_m: texel_per_m,
        });
        Self {
            scene,
            plate_front: ctx.geo[PLATE].glossy,
            half: scene.plate_half_m() as f32,
            cells: m.cells,
            cell_table,
            cell_rows: CellRows::new(cell_table, side, ALBEDO_WHITE as f32, ALBEDO_BLACK as f32),
            cell_per_m,
            half_marker: 0.5 * m.size_m as f32,
            // Footprint in cells: the width of the box filter over the cell grid.
            inv_wu: 1.0 / (footprint.0 as f32 * cell_per_m).max(1e-6),
            inv_wv: 1.0 / (footprint.1 as f32 * cell_per_m).max(1e-6),
            albedo_back: scene.plate_back_albedo() as f32,
            texel_per_m,
            caustics,
            lit,
            plate_caustics,
            isa,
        }
    }
}

impl PixelConsts<'_> {
    /// The plate's front along a span: its forms (D, Nu, Nv) and light fields, each at
    /// the span's first pixel and per pixel.
    #[inline(always)]
    fn plate_front(
        &self,
        forms: ([f32; 3], [f32; 3]),
        light: ([f32; 3], [f32; 3]),
    ) -> PlateRun<'_> {
        let ((f0, fd), (a0, ad)) = (forms, light);
        let ramp = |c: usize, at: &[f32; 3], step: &[f32; 3]| Ramp {
            at: at[c],
            step: step[c],
        };
        PlateRun {
            d: ramp(0, &f0, &fd),
            nu: ramp(1, &f0, &fd),
            nv: ramp(2, &f0, &fd),
            half_marker: self.half_marker,
            cell_per_m: self.cell_per_m,
            inv_wu: self.inv_wu,
            inv_wv: self.inv_wv,
            cells: self.cell_table,
            rows: self.cell_rows.as_ref(),
            side: self.cells as i32 + 2,
            caustic: self.plate_caustics,
            ambient: ramp(0, &a0, &ad),
            lamp: ramp(1, &a0, &ad),
            add: ramp(2, &a0, &ad),
        }
    }
}

/// The three fields of a cell-row node entry at vertical weight `fy`.
#[inline(always)]
fn cell_at(c: &[f32; 6], fy: f32) -> [f32; 3] {
    [c[0] + c[3] * fy, c[1] + c[4] * fy, c[2] + c[5] * fy]
}

/// A texel coordinate (texels) in 16.16 fixed point, wrapping in i32 like the texture
/// (the clamp only matters beyond 32 000 texels, far past what the water lets through).
#[allow(clippy::manual_clamp)]
#[inline(always)]
fn fix16(t: f32) -> i32 {
    // max/min (not clamp) so a NaN lands on -2e9; then the value is in range and the
    // conversion needs no saturation code (it stays packed).
    let x = (t * 65536.0).max(-2.0e9).min(2.0e9);
    // SAFETY: x is finite and within i32's range.
    unsafe { x.to_int_unchecked::<i32>() }
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
        let map = map::MapPlates::new(&node_x, &node_y);
        Self {
            width: w,
            height: h,
            nx,
            node_x,
            node_y,
            fields: vec![[0.0; 3]; nx * ny * NSURF],
            stamp: vec![u32::MAX; nx * ny * NSURF],
            frame_id: 0,
            cell_forms: vec![0.0; 2 * 9 * nx],
            row_forms: vec![0.0; 9 * nx],
            row_mask: vec![0; nx],
            row_mask32: vec![0; nx],
            row_walks: vec![0; 2 * WALKS * nx],
            row_affine: vec![false; 2 * nx],
            cell_fields: vec![[0.0; 6]; NSURF * nx],
            cell_stamp: vec![u32::MAX; NSURF * nx],
            cell_id: 0,
            cell_range: [(1, 0); NSURF],
            rock_cells: vec![[0.0; 6]; 2 * nx],
            row_mean: vec![0.0; w],
            zero_noise: vec![0; w],
            cell_table: Vec::new(),
            lit: LitTexture::default(),
            map,
            isa: Isa::detect(false),
        }
    }

    /// Run the portable loops even on a CPU with AVX2 (tests compare the two builds).
    pub(crate) fn set_portable(&mut self, portable: bool) {
        self.isa = Isa::detect(portable);
    }

    pub(crate) fn set_loops(&mut self, want: RenderLoops) -> RenderLoops {
        let want = match want {
            #[cfg(target_arch = "x86_64")]
            RenderLoops::Avx2 => Isa::Avx2,
            #[cfg(target_arch = "x86_64")]
            RenderLoops::Avx512 => Isa::Avx512,
            _ => Isa::Portable,
        };
        self.isa = Isa::best_up_to(want);
        self.loops()
    }

    pub(crate) fn loops(&self) -> RenderLoops {
        match self.isa {
            Isa::Portable => RenderLoops::Portable,
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => RenderLoops::Avx2,
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => RenderLoops::Avx512,
        }
    }

    /// The light fields of `surf` at node `node`, computed on first use this frame.
    #[inline(always)]
    fn node_fields(&mut self, ctx: &FrameCtx, node: usize, surf: usize) -> [f32; 3] {
        let idx = node * NSURF + surf;
        if self.stamp[idx] == self.frame_id {
            return self.fields[idx];
        }
        self.node_fields_new(ctx, node, surf)
    }

    /// `node_fields` the first time this frame (kept out of line: the lookup above is
    /// what most calls do).
    #[inline(never)]
    fn node_fields_new(&mut self, ctx: &FrameCtx, node: usize, surf: usize) -> [f32; 3] {
        let idx = node * NSURF + surf;
        // Adaptive light grid: a node halfway between two nodes takes their mean where
        // the light along that line is flat or nearly linear; where it curves (a beam's
        // edge or spot, the glare) the node is shaded. The shaded base grid is fine
        // enough for the narrowest lamp feature of the frame (`light_base`), so its
        // nodes and their curvature see every feature.
        let (nx, ny) = (self.nx, self.node_x.len() / self.nx);
        let (i, j) = (node % nx, node / nx);
        // Nodes on the base grid (every `light_base`-th node both ways) are shaded; any
        // other node lies halfway between two nodes `s` apart on its row or column (s the
        // lowest set bit of its index there; the smaller of the two), and, where they
        // exist, between two more 3 s apart (for the curvature test below).
        let base = ctx.light_base;
        let step = |k: usize| (!k.is_multiple_of(base)).then_some(k & k.wrapping_neg());
        let h = step(i).filter(|&s| i + s < nx);
        let v = step(j).filter(|&t| j + t < ny);
        let line = |d: usize, k: usize, n: usize, s: usize| {
            let outer = (k >= 3 * s && k + 3 * s < n).then(|| (node - 3 * s * d, node + 3 * s * d));
            Some((node - s * d, node + s * d, outer))
        };
        let pair = match (h, v) {
            (Some(s), Some(t)) if t < s => line(nx, j, ny, t),
            (Some(s), _) => line(1, i, nx, s),
            (None, Some(t)) => line(nx, j, ny, t),
            (None, None) => None,
        };
        if let Some((a, b, outer)) = pair {
            let (fa, fb) = (
                self.node_fields(ctx, a, surf),
                self.node_fields(ctx, b, surf),
            );
            let close = match outer {
                // The mean's error is about an eighth of the second difference over the
                // nodes at -3, -1, 1 and 3 (the larger of the two, so an inflection
                // between them cannot hide a curve): flat or nearly linear light (most of
                // the background, the falloff of wide lamps) is interpolated, a peak
                // between two equal nodes (a narrow lamp's spot) is not.
                Some((a3, b3)) => {
                    let (fa3, fb3) = (
                        self.node_fields(ctx, a3, surf),
                        self.node_fields(ctx, b3, surf),
                    );
                    (0..3).all(|c| {
                        let left = fa3[c] - 2.0 * fa[c] + fb[c];
                        let right = fa[c] - 2.0 * fb[c] + fb3[c];
                        left.abs().max(right.abs()) * 0.125
                            <= LIGHT_CURVE_TOL * fa[c].abs().max(fb[c].abs()) + LIGHT_CURVE_ABS_E
                    })
                }
                // Near the image border: the two nodes must agree.
                None => (0..3).all(|c| {
                    (fa[c] - fb[c]).abs()
                        <= LIGHT_REL_TOL * fa[c].abs().max(fb[c].abs()) + LIGHT_ABS_TOL_E
                }),
            };
            if close {
                let f = [
                    0.5 * (fa[0] + fb[0]),
                    0.5 * (fa[1] + fb[1]),
                    0.5 * (fa[2] + fb[2]),
                ];
                self.fields[idx] = f;
                self.stamp[idx] = self.frame_id;
                return f;
            }
        }
        let f = self.shade_node(ctx, node, surf);
        self.fields[idx] = f;
        self.stamp[idx] = self.frame_id;
        f
    }

    /// The light fields of `surf` at node `node`, shaded (no interpolation).
    fn shade_node(&self, ctx: &FrameCtx, node: usize, surf: usize) -> [f32; 3] {
        let (x, y) = (self.node_x[node], self.node_y[node]);
        if surf == WATER {
            ctx.shade_water(x, y)
        } else {
            ctx.shade_on(&ctx.geo[surf], x, y)
        }
    }

    /// Make the cell fields of `surf` valid at nodes `i0..=i1` of cell row `j`.
    #[inline(always)]
    fn ensure_cells(&mut self, ctx: &FrameCtx, surf: usize, i0: usize, i1: usize, j: usize) {
        let (lo, hi) = self.cell_range[surf];
        if lo <= i0 && i1 <= hi {
            return;
        }
        self.fill_cells(ctx, surf, i0, i1, j);
    }

    /// `ensure_cells` outside the known range (out of line: most calls are inside it).
    #[inline(never)]
    fn fill_cells(&mut self, ctx: &FrameCtx, surf: usize, i0: usize, i1: usize, j: usize) {
        let (lo, hi) = self.cell_range[surf];
        let nx = self.nx;
        for i in i0..=i1 {
            let idx = surf * nx + i;
            if self.cell_stamp[idx] == self.cell_id {
                continue;
            }
            let n0 = self.node_fields(ctx, j * nx + i, surf);
            let n1 = self.node_fields(ctx, (j + 1) * nx + i, surf);
            let cell = top_and_change(n0, n1);
            self.cell_fields[idx] = cell;
            if let Some(p) = surf.checked_sub(WALL).filter(|&p| p < 2) {
                self.rock_cells[p * nx + i] = fold_rock_cell(&cell, ctx.rock_fold);
            }
            self.cell_stamp[idx] = self.cell_id;
        }
        // Grow the known range when the runs touch it (the usual case: the same runs
        // row after row), else start a new one.
        self.cell_range[surf] = if lo <= hi && i0 <= hi + 1 && lo <= i1 + 1 {
            (lo.min(i0), hi.max(i1))
        } else {
            (i0, i1)
        };
    }

    /// Fields of `surf` at the left end of span `i` of the current row (vertical weight
    /// `fy` in cell row `j`) and their step per pixel.
    #[inline]
    fn span_fields(
        &mut self,
        ctx: &FrameCtx,
        i: usize,
        j: usize,
        fy: f32,
        surf: usize,
    ) -> ([f32; 3], [f32; 3]) {
        self.ensure_cells(ctx, surf, i, i + 1, j);
        let c = &self.cell_fields[surf * self.nx + i..surf * self.nx + i + 2];
        let (l, r) = (cell_at(&c[0], fy), cell_at(&c[1], fy));
        let mut df = [0f32; 3];
        for c in 0..3 {
            df[c] = (r[c] - l[c]) * (1.0 / GRID as f32);
        }
        (l, df)
    }

    /// The planes' forms on grid rows `j` and `j + 1` (see `cell_forms`).
    fn cell_row_forms(&mut self, forms: &[PlaneForms; 3], j: usize) {
        let nx = self.nx;
        let (top, delta) = self.cell_forms.split_at_mut(9 * nx);
        let (x0, x1) = self.node_x[j * nx..(j + 2) * nx].split_at(nx);
        let (y0, y1) = self.node_y[j * nx..(j + 2) * nx].split_at(nx);
        for (k, fm) in forms.iter().enumerate() {
            for (c, coef) in [&fm.d, &fm.u, &fm.v].into_iter().enumerate() {
                let at = (k * 3 + c) * nx;
                let (t, d) = (&mut top[at..at + nx], &mut delta[at..at + nx]);
                for i in 0..nx {
                    let (a, b) = (form(coef, x0[i], y0[i]), form(coef, x1[i], y1[i]));
                    t[i] = a;
                    d[i] = b - a;
                }
            }
        }
    }

    /// The current row at its nodes: forms, test signs, texel walks (plain loops over
    /// arrays, so they run on packed registers).
    #[inline(always)]
    fn row_nodes(&mut self, ctx: &FrameCtx, pc: &PixelConsts, fy: f32) {
        let nx = self.nx;
        let (top, delta) = self.cell_forms.split_at(9 * nx);
        for ((f, &a), &d) in self.row_forms.iter_mut().zip(top).zip(delta) {
            *f = a + d * fy;
        }
        // The signs of the linear tests that pick the surface (see `Cuts`): a span whose
        // two nodes agree on all of them shows one surface.
        let half = pc.half;
        let (hw, hs) = (ctx.forms[WALL].h, ctx.forms[SEABED].h);
        let f = |k: usize, c: usize| &self.row_forms[(k * 3 + c) * nx..(k * 3 + c + 1) * nx];
        let (fdp, fup, fvp, fdw, fds) = (
            f(PLATE, 0),
            f(PLATE, 1),
            f(PLATE, 2),
            f(WALL, 0),
            f(SEABED, 0),
        );
        // In 32-bit lanes (as wide as the forms, so the loop runs packed), then narrowed.
        let masks = self.row_mask32[..nx].iter_mut().zip(fdp).zip(fup).zip(fvp);
        for ((((m, &dp), &up), &vp), (&dw, &ds)) in masks.zip(fdw.iter().zip(fds)) {
            *m = (dp > 0.0) as u32
                | ((up - half * dp > 0.0) as u32) << 1
                | ((up + half * dp > 0.0) as u32) << 2
                | ((vp - half * dp > 0.0) as u32) << 3
                | ((vp + half * dp > 0.0) as u32) << 4
                | ((dw > 0.0) as u32) << 5
                | ((ds > 0.0) as u32) << 6
                | ((hw * ds - hs * dw > 0.0) as u32) << 7;
        }
        for (m, &w) in self.row_mask[..nx].iter_mut().zip(&self.row_mask32[..nx]) {
            *m = w as u8;
        }
        // Texel walks of the rock planes at the nodes.
        let tk = pc.texel_per_m;
        for (p, k) in [WALL, SEABED].into_iter().enumerate() {
            let d = &self.row_forms[k * 3 * nx..(k * 3 + 1) * nx];
            let nu = &self.row_forms[(k * 3 + 1) * nx..(k * 3 + 2) * nx];
            let nv = &self.row_forms[(k * 3 + 2) * nx..(k * 3 + 3) * nx];
            let ok = &mut self.row_affine[p * nx..(p + 1) * nx];
            let walks = &mut self.row_walks[p * WALKS * nx..(p + 1) * WALKS * nx];
            let (ru, rv) = walks.split_at_mut(nx);
            let inv = |d: f32| if d > 1e-6 { 1.0 / d } else { 0.0 };
            let planes = d.iter().zip(nu).zip(nv);
            for ((((&d, &nu), &nv), ok), (ru, rv)) in planes.zip(ok).zip(ru.iter_mut().zip(rv)) {
                *ok = d > 1e-6;
                let k = inv(d);
                *ru = fix16(nu * k * tk);
                *rv = fix16(nv * k * tk);
            }
        }
    }

    pub(crate) fn render(&mut self, input: &FrameInput, rng: &mut XorShift64Star, out: &mut Frame) {
        #[cfg(target_arch = "x86_64")]
        match self.isa {
            // SAFETY: `Isa::Avx2` is only chosen when the CPU has AVX2.
            Isa::Avx2 => unsafe { return self.render_avx2(input, rng, out) },
            // SAFETY: `Isa::Avx512` is only chosen when the CPU has AVX2 and AVX-512.
            Isa::Avx512 => unsafe { return self.render_avx512(input, rng, out) },
            Isa::Portable => {}
        }
        self.render_impl(input, rng, out)
    }

    /// The same code compiled for AVX-512 (the rock loops take their 16-lane build).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl")]
    unsafe fn render_avx512(
        &mut self,
        input: &FrameInput,
        rng: &mut XorShift64Star,
        out: &mut Frame,
    ) {
        self.render_impl(input, rng, out)
    }

    /// The same code compiled for AVX2, so its plain loops also run eight wide.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn render_avx2(
        &mut self,
        input: &FrameInput,
        rng: &mut XorShift64Star,
        out: &mut Frame,
    ) {
        self.render_impl(input, rng, out)
    }

    #[inline(always)]
    fn render_impl(&mut self, input: &FrameInput, rng: &mut XorShift64Star, out: &mut Frame) {
        let FrameInput {
            model,
            scene,
            t_wc,
            lamps,
            time_s,
            e_per_unit,
            tables,
        } = *input;
        self.next_frame();
        let (geo, forms) = frame_planes(scene, t_wc);
        let caustics = CausticFrame::new(scene, time_s);
        // Rock and both webs at this frame's drifts in one texture (a few tenths of a
        // millisecond; it saves two texel reads a caustic pixel). Rebuilt every frame:
        // the webs drift a few texels a frame.
        let mut lit = std::mem::take(&mut self.lit);
        if caustics.on {
            lit.build(&scene.rock, &scene.caustic, caustics.shift);
        }
        let ctx = FrameCtx {
            scene,
            t_wc,
            lamps,
            geo,
            forms,
            e_per_unit,
            light_base: light_base(model, scene, t_wc, lamps),
            rock_fold: rock_fold(scene, &caustics, &lit),
        };
        // The cell table, bordered by the white plate (refilled each frame: the scene is
        // the caller's; no allocation once its size is reached).
        let mut cell_table = std::mem::take(&mut self.cell_table);
        fill_cell_table(&mut cell_table, scene.marker());
        let pc = PixelConsts::new(model, &ctx, caustics, &lit, &cell_table, self.isa);
        let sensor = sensor_row(tables);
        let valid = [forms[PLATE].valid, forms[WALL].valid, forms[SEABED].valid];
        let surf_of_mask: [usize; 256] = std::array::from_fn(|m| surface_of_mask(m as u8, valid));
        let (w, h) = (self.width, self.height);
        let mut map = std::mem::take(&mut self.map);
        map.prepare(model, &ctx, &self.nodes());
        for (py, row) in out.data.chunks_exact_mut(w).enumerate().take(h) {
            self.shade_row(&ctx, &pc, &surf_of_mask, py);
            let mut row_mean = std::mem::take(&mut self.row_mean);
            map.overlay_row(&ctx, &pc, &self.nodes(), py, &mut row_mean);
            self.row_mean = row_mean;
            // The sensor: windows of the two noise fields at random offsets per row.
            let noise = if tables.noise {
                noise_windows(&tables.noise_fields, rng.next_u64(), w)
            } else {
                [&self.zero_noise[..], &self.zero_noise[..]]
            };
            sensor_run(self.isa, row, &self.row_mean, noise, &sensor);
        }
        self.cell_table = cell_table;
        self.lit = lit;
        self.map = map;
    }

    /// The grid's rays, for the map's plates.
    fn nodes(&self) -> map::Nodes<'_> {
        map::Nodes {
            x: &self.node_x,
            y: &self.node_y,
            nx: self.nx,
            width: self.width,
            height: self.height,
        }
    }

    /// A new frame id for the light-field stamps (they restart before the id wraps).
    #[inline(always)]
    fn next_frame(&mut self) {
        self.frame_id = self.frame_id.wrapping_add(1);
        if self.frame_id == u32::MAX {
            self.stamp.fill(u32::MAX - 1);
            self.frame_id = 0;
        }
    }

    /// A new cell row `j`: every cached cell field is stale.
    #[inline(always)]
    fn start_cell_row(&mut self, ctx: &FrameCtx, j: usize) {
        self.cell_id = self.cell_id.wrapping_add(1);
        if self.cell_id == u32::MAX {
            self.cell_stamp.fill(u32::MAX - 1);
            self.cell_id = 0;
        }
        self.cell_range = [(1, 0); NSURF];
        self.cell_row_forms(&ctx.forms, j);
    }

    /// Mean electrons of image row `py` into `row_mean`: the row's nodes, then its spans,
    /// a run of spans on one surface at a time.
    #[inline(always)]
    fn shade_row(
        &mut self,
        ctx: &FrameCtx,
        pc: &PixelConsts,
        surf_of_mask: &[usize; 256],
        py: usize,
    ) {
        let j = py / GRID;
        if py == 0 || j != (py - 1) / GRID {
            self.start_cell_row(ctx, j);
        }
        let fy = (py - j * GRID) as f32 * (1.0 / GRID as f32);
        self.row_nodes(ctx, pc, fy);
        let mut row_mean = std::mem::take(&mut self.row_mean);
        let (w, nx) = (self.width, self.nx);
        let spans = nx - 1;
        let mut i = 0;
        while i < spans && i * GRID < w {
            let x0 = i * GRID;
            let mk = self.row_mask[i];
            if mk != self.row_mask[i + 1] {
                let x1 = (x0 + GRID).min(w);
                self.mixed_span(ctx, pc, i, j, fy, &mut row_mean[x0..x1]);
                i += 1;
                continue;
            }
            // A run of spans whose nodes all agree on every surface test: one
            // surface over the whole run, shaded by the packed loops.
            let i1 = run_end(&self.row_mask, i + 1, spans.min(w.div_ceil(GRID)));
            let surf = surf_of_mask[mk as usize];
            self.shade_run(ctx, pc, surf, (i, i1), (j, fy), &mut row_mean);
            i = i1;
        }
        self.row_mean = row_mean;
    }

    /// Spans `i..i1` of the current row, all on surface `surf`, into `row_mean` (the
    /// whole row); `(j, fy)` is the cell row and the row's weight in it.
    #[inline(always)]
    fn shade_run(
        &mut self,
        ctx: &FrameCtx,
        pc: &PixelConsts,
        surf: usize,
        (i, i1): (usize, usize),
        (j, fy): (usize, f32),
        row_mean: &mut [f32],
    ) {
        let (w, nx, isa) = (self.width, self.nx, self.isa);
        let x0 = i * GRID;
        let p = surf.wrapping_sub(WALL);
        let affine = p < 2 && self.row_affine[p * nx + i..=p * nx + i1].iter().all(|&a| a);
        let plate = surf == PLATE && pc.plate_front;
        if surf == WATER || affine || plate {
            self.ensure_cells(ctx, surf, i, i1, j);
        }
        let out = &mut row_mean[x0..(i1 * GRID).min(w)];
        if plate {
            // Inside the plate's square on every node: no surface border to cut.
            for (k, o) in (i..i1).zip(out.chunks_mut(GRID)) {
                let light = self.span_fields(ctx, k, j, fy, PLATE);
                plate_run(isa, o, 0, &pc.plate_front(self.span_forms(PLATE, k), light));
            }
        } else if surf == WATER {
            let f = &self.cell_fields[surf * nx + i..=surf * nx + i1];
            for (s, o) in out.chunks_mut(GRID).enumerate() {
                let (a, b) = (f[s][2] + f[s][5] * fy, f[s + 1][2] + f[s + 1][5] * fy);
                ramp_run(
                    o,
                    Ramp {
                        at: a,
                        step: (b - a) * (1.0 / GRID as f32),
                    },
                );
            }
        } else if affine {
            let wk = |k: usize| {
                let base = (p * WALKS + k) * nx;
                &self.row_walks[base + i..=base + i1]
            };
            let c = pc.caustics.on.then_some(pc.lit);
            let nodes = RockNodes {
                cells: &self.rock_cells[p * nx + i..=p * nx + i1],
                fy,
                walks: [wk(0), wk(1)],
            };
            rock_nodes_run(isa, out, 0, &nodes, &ctx.scene.rock, c);
        } else {
            for k in i..i1 {
                let x1 = ((k + 1) * GRID).min(w);
                self.mixed_span(ctx, pc, k, j, fy, &mut row_mean[k * GRID..x1]);
            }
        }
    }

    /// The linear forms (D, Nu, Nv) of plane `k` at the left end of span `i` of the
    /// current row and their step per pixel.
    #[inline(always)]
    fn span_forms(&self, k: usize, i: usize) -> ([f32; 3], [f32; 3]) {
        let nx = self.nx;
        let (mut f0, mut df) = ([0f32; 3], [0f32; 3]);
        for c in 0..3 {
            let a = self.row_forms[(k * 3 + c) * nx + i];
            let b = self.row_forms[(k * 3 + c) * nx + i + 1];
            f0[c] = a;
            df[c] = (b - a) * (1.0 / GRID as f32);
        }
        (f0, df)
    }

    /// A span that may show several surfaces (or the plate, or the horizon): split at
    /// the roots of the surface tests into runs of one surface, each shaded per pixel.
    #[inline(always)]
    fn mixed_span(
        &mut self,
        ctx: &FrameCtx,
        pc: &PixelConsts,
        i: usize,
        j: usize,
        fy: f32,
        out: &mut [f32],
    ) {
        let n = out.len();
        let nx = self.nx;
        let half = pc.half;
        let scene = pc.scene;
        let caustics = &pc.caustics;
        let rock = &scene.rock;
        // Linear forms of every plane at the span start and their step per pixel.
        let mut sp = Span::default();
        for k in 0..3 {
            (sp.f0[k], sp.df[k]) = self.span_forms(k, i);
        }
        // Every test that picks the surface is the sign of a linear function of the
        // pixel (u = Nu / D is monotonic while D > 0): between their roots the surface
        // is the same, so the span splits into runs of one surface.
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
        let mut start = 0usize;
        for c in 0..=cuts.n {
            let end = if c < cuts.n { cuts.at[c] } else { n };
            if end <= start {
                continue;
            }
            let surf = classify(&sp, &ctx.forms, half, ((start + end - 1) / 2) as f32);
            if !ready[surf] {
                lf[surf] = self.span_fields(ctx, i, j, fy, surf);
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
                PLATE if pc.plate_front => {
                    plate_run(pc.isa, run, start, &pc.plate_front((p0, pd), (a0, ad)));
                }
                PLATE => {
                    for (t, m) in run.iter_mut().enumerate() {
                        let t = first + t as f32;
                        *m = pc.albedo_back * (a0[0] + ad[0] * t + a0[1] + ad[1] * t)
                            + a0[2]
                            + ad[2] * t;
                    }
                }
                k => {
                    let p = k - WALL;
                    if self.row_affine[p * nx + i] && self.row_affine[p * nx + i + 1] {
                        // The packed runs' walks and fields, from this run's first pixel.
                        let wk = |w: usize| {
                            let base = (p * WALKS + w) * nx;
                            &self.row_walks[base + i..=base + i + 1]
                        };
                        let c = caustics.on.then_some(pc.lit);
                        let nodes = RockNodes {
                            cells: &self.rock_cells[p * nx + i..=p * nx + i + 1],
                            fy,
                            walks: [wk(0), wk(1)],
                        };
                        rock_nodes_run(pc.isa, run, start, &nodes, rock, c);
                    } else {
                        // Near the horizon: exact per pixel.
                        let (f0, fd) = (sp.f0[k], sp.df[k]);
                        let tk = pc.texel_per_m;
                        for (t, m) in run.iter_mut().enumerate() {
                            let t = first + t as f32;
                            let inv = 1.0 / (f0[0] + fd[0] * t);
                            let u = (f0[1] + fd[1] * t) * inv;
                            let v = (f0[2] + fd[2] * t) * inv;
                            let albedo = rock.at(floor_i32(u * tk), floor_i32(v * tk));
                            let c = if caustics.on {
                                caustics.at(pc.lit, tk, u, v)
                            } else {
                                1.0
                            };
                            let f = |c: usize| a0[c] + ad[c] * t;
                            *m = albedo * (f(0) * c + f(1)) + f(2);
                        }
                    }
                }
            }
            start = end;
        }
    }
}

/// How the rock planes' fields fold into the rock loops this frame.
#[inline(always)]
fn rock_fold(scene: &Scene, caustics: &CausticFrame, lit: &LitTexture) -> RockFold {
    if caustics.on {
        RockFold::caustic(caustics.strength, lit.caustic_offset, lit.caustic_scale)
    } else {
        RockFold::Plain {
            scale: scene.rock.scale,
            offset: scene.rock.offset,
        }
    }
}

/// The marker's cell albedos with a one-cell white border (the plate), row-major,
/// `(cells + 2)^2` entries; no allocation once `table` has held that many.
#[inline(always)]
fn fill_cell_table(table: &mut Vec<f32>, m: &MarkerSpec) {
    let side = m.cells + 2;
    table.clear();
    table.extend((0..side * side).map(|k| {
        let (ci, cj) = ((k % side) as isize - 1, (k / side) as isize - 1);
        let inside = ci >= 0 && cj >= 0 && (ci as usize) < m.cells && (cj as usize) < m.cells;
        let white = !inside
            || m.white
                .get(cj as usize * m.cells + ci as usize)
                .copied()
                .unwrap_or(true);
        if white {
            ALBEDO_WHITE as f32
        } else {
            ALBEDO_BLACK as f32
        }
    }));
}

/// The sensor's per-frame constants for `sensor_run`.
#[inline(always)]
fn sensor_row(tables: &SensorTables) -> SensorRow<'_> {
    SensorRow {
        read_var: tables.read_var_e2,
        per_s: tables.lut_per_s,
        top: (RESPONSE_LUT_LEN - 1) as f32,
        lut: &tables.response_lut,
        linear: tables.linear,
    }
}

/// A row's windows of the two noise fields, `w` long, at offsets drawn from `bits`
/// (high and low half).
#[inline(always)]
fn noise_windows(fields: &[Vec<i16>; 2], bits: u64, w: usize) -> [&[i16]; 2] {
    fn window(field: &[i16], r: u64, w: usize) -> &[i16] {
        let room = field.len().saturating_sub(w) + 1;
        let off = r as usize % room;
        &field[off..(off + w).min(field.len())]
    }
    let [a, b] = fields;
    [window(a, bits >> 32, w), window(b, bits & 0xFFFF_FFFF, w)]
}

/// The first node `k` in `from..end` where `mask[k + 1] != mask[k]`, else `end` (the
/// end of a run of equal masks that holds `from - 1` and `from`). Eight nodes a step:
/// one xor of two overlapping words finds the first change (a run is mostly whole rows
/// of one surface).
#[inline(always)]
fn run_end(mask: &[u8], from: usize, end: usize) -> usize {
    let mut k = from;
    while k < end && k + 9 <= mask.len() {
        let word = |a: usize| u64::from_le_bytes(mask[a..a + 8].try_into().unwrap_or([0; 8]));
        let x = word(k) ^ word(k + 1);
        if x != 0 {
            return (k + x.trailing_zeros() as usize / 8).min(end);
        }
        k += 8;
    }
    while k < end && mask[k + 1] == mask[k] {
        k += 1;
    }
    k.min(end)
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

/// The surface seen where the surface tests have the signs `mask` (bits as in
/// `FastRenderer::row_nodes`), `valid` the planes that face the camera: what
/// [`classify`] decides from the same signs.
fn surface_of_mask(mask: u8, valid: [bool; 3]) -> usize {
    let bit = |b: u32| mask & (1 << b) != 0;
    // In front, |Nu| <= half D and |Nv| <= half D.
    if valid[PLATE] && bit(0) && !bit(1) && bit(2) && !bit(3) && bit(4) {
        return PLATE;
    }
    let wall_ok = valid[WALL] && bit(5);
    let sea_ok = valid[SEABED] && bit(6);
    // The wall is nearer when h_w D_s - h_s D_w < 0.
    if wall_ok && (!sea_ok || !bit(7)) {
        WALL
    } else if sea_ok {
        SEABED
    } else {
        WATER
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
    /// Each web's drift, texels.
    shift: [(i32, i32); 2],
}

impl CausticFrame {
    fn new(scene: &Scene, t: f64) -> Self {
        let p = scene.caustic_params(t);
        Self {
            on: p.strength > 0.0,
            strength: p.strength as f32,
            shift: p.shift,
        }
    }

    /// Caustic factor at surface coordinates (u, v), metres, from the frame's `lit`
    /// (`k` rock texels per metre: the webs lie on the rock's grid).
    #[inline(always)]
    fn at(&self, lit: &LitTexture, k: f32, u: f32, v: f32) -> f32 {
        let b = lit.caustic_at(floor_i32(u * k), floor_i32(v * k));
        1.0 + self.strength * (b - 1.0)
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

/// Width and height (metres, marker frame) of one pixel's footprint on the plate at
/// `t_wm` near its centre: the bounding box of the pixel's image on the plate.
fn plate_footprint(
    model: &CameraModel,
    t_wc: &Isometry3<f64>,
    t_wm: &Isometry3<f64>,
    forms: &PlaneForms,
) -> (f64, f64) {
    let p_c = t_wc.inverse_transform_point(&t_wm.translation.vector.into());
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::sensor::electrons_per_unit;
    use crate::scene::{LightingConfig, LightingScenario, MarkerSpec, WaterConfig};
    use markhold_exposure::ResponseModel;
    use nalgebra::Translation3;

    /// Every node the adaptive light grid interpolates, against shading it: at the
    /// production resolution, 1.2 m from the marker, in the lightings whose fields change
    /// fastest (the vehicle's lamps in low light, the marker's lamp in adversarial). The
    /// grid's first rule (32-pixel base, interpolate where the two nodes agree within 2 %)
    /// fails both ways (shading too many nodes under the vehicle's lamps, missing the
    /// marker lamp's spot), and a 64-pixel base under the marker's lamp loses its spot at
    /// 480x360: figures in docs/design/hil.md, "Light grid".
    #[test]
    fn run_end_finds_the_first_change_like_a_scan() {
        // Masks with runs of every length from 1 to 20 around the word steps.
        let mut mask = Vec::new();
        for (n, len) in (1..=20usize).chain([40, 3, 1, 1, 64]).enumerate() {
            mask.extend(std::iter::repeat_n((n % 7) as u8, len));
        }
        for len in [2usize, 9, 10, 17, mask.len()] {
            let m = &mask[..len];
            for from in 1..len {
                for end in from..len {
                    let mut want = from;
                    while want < end && m[want + 1] == m[want] {
                        want += 1;
                    }
                    assert_eq!(
                        run_end(m, from, end),
                        want,
                        "len {len} from {from} end {end}"
                    );
                }
            }
        }
    }

    #[test]
    fn interpolated_light_nodes_stay_close_to_shading() {
        let model = CameraModel::blackfly_s(ResponseModel::Gamma { gamma: 2.2 });
        let marker_at = Vector3::new(0.0, 0.0, 4.0);
        let south = Vector3::new(-1.0, 0.0, 0.0);
        // Marker face toward the south, its y axis up (NED: -z).
        let t_wm = Isometry3::face_towards(
            &Point3::from(marker_at),
            &Point3::from(marker_at + south),
            &Vector3::new(0.0, 0.0, -1.0),
        );
        let cells = 8;
        let marker = MarkerSpec {
            cells,
            white: (0..cells * cells).map(|k| k % 3 == 0).collect(),
            size_m: 0.2,
            plate_margin_m: 0.04,
        };
        // Lighting, camera distance, exposure, the base grid, the least share of nodes
        // interpolated.
        for (scenario, dist_m, exposure_us, base, min_share) in [
            (LightingScenario::Low, 1.2, 30_000.0, LIGHT_BASE_WIDE, 0.8),
            (
                LightingScenario::Adversarial,
                1.2,
                800.0,
                LIGHT_BASE_NARROW,
                0.6,
            ),
            // The marker lamp's spot small in the picture.
            (
                LightingScenario::Adversarial,
                2.5,
                800.0,
                LIGHT_BASE_NARROW,
                0.6,
            ),
            (LightingScenario::Normal, 1.2, 3000.0, LIGHT_BASE_WIDE, 0.8),
        ] {
            let lighting = LightingConfig {
                scenario,
                ..LightingConfig::default()
            };
            let scene = Scene::new(&WaterConfig::default(), &lighting, marker.clone(), t_wm, 5)
                .expect("valid scene");
            // Camera south of the marker, a little off its axis, looking north (x
            // right = east, y down).
            let eye = marker_at + south * dist_m + Vector3::new(0.0, 0.1, -0.05);
            let t_wc = Isometry3::face_towards(
                &Point3::from(eye),
                &Point3::from(marker_at + Vector3::new(0.0, 0.15, 0.0)),
                &Vector3::new(0.0, 0.0, 1.0),
            );
            // The vehicle 0.2 m behind the camera, body axes forward-right-down (its
            // lamps point along the camera's axis).
            let body = nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(
                0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0,
            ));
            let t_wv = t_wc
                * Isometry3::from_parts(
                    Translation3::new(0.0, 0.0, -0.2),
                    nalgebra::UnitQuaternion::from_rotation_matrix(&body),
                );
            let mut lamps = Vec::new();
            scene.lamps_for(&t_wv, &mut lamps);
            let (geo, forms) = frame_planes(&scene, &t_wc);
            let ctx = FrameCtx {
                scene: &scene,
                t_wc: &t_wc,
                lamps: &lamps,
                geo,
                forms,
                e_per_unit: electrons_per_unit(&model, exposure_us),
                light_base: light_base(&model, &scene, &t_wc, &lamps),
                // Not read by the node fields this test checks.
                rock_fold: RockFold::Plain {
                    scale: 1.0,
                    offset: 0.0,
                },
            };
            assert_eq!(ctx.light_base, base, "{scenario} at {dist_m} m");
            let mut r = FastRenderer::new(&model);
            r.frame_id = 1;
            let (mut interpolated, mut worst_rel, mut worst_sd) = (0usize, 0f32, 0f32);
            let read_var = (model.sensor.read_noise_e * model.sensor.read_noise_e) as f32;
            let n = r.node_x.len();
            let half = scene.plate_half_m() as f32;
            for node in 0..r.node_x.len() {
                // The surface the node's ray sees (the fields the pixels there use).
                let (x, y) = (r.node_x[node], r.node_y[node]);
                let mut sp = Span::default();
                for (f0, fm) in sp.f0.iter_mut().zip(&forms) {
                    *f0 = [form(&fm.d, x, y), form(&fm.u, x, y), form(&fm.v, x, y)];
                }
                let surf = classify(&sp, &forms, half, 0.0);
                let got = r.node_fields(&ctx, node, surf);
                let want = r.shade_node(&ctx, node, surf);
                interpolated += (got != want) as usize;
                // In units of the noise of a white pixel there (shot and read noise).
                let total = want.iter().sum::<f32>().max(0.0);
                let sd = (total + read_var).sqrt();
                for c in 0..3 {
                    worst_rel = worst_rel.max((got[c] - want[c]).abs() / (total + 1.0));
                    worst_sd = worst_sd.max((got[c] - want[c]).abs() / sd);
                }
            }
            let share = interpolated as f64 / n as f64;
            println!(
                "{scenario} at {dist_m} m: {:.1} % of the nodes interpolated, worst {:.3} % of the light, {:.3} noise sd",
                100.0 * share,
                100.0 * worst_rel,
                worst_sd
            );
            assert!(
                worst_sd < 0.1,
                "{scenario}: a node {worst_sd:.3} noise sd off"
            );
            assert!(
                share > min_share,
                "{scenario}: only {:.1} % interpolated",
                100.0 * share
            );
        }
    }
}
