//! The map's other plates (every marker of the site but the origin one) over the row the
//! origin scene drew. Each plate is a plane like the origin plate: its forms advance
//! linearly along the 16-pixel spans, its light is shaded at the grid nodes it may cover
//! and interpolated, and its cells go through the same box-filtered plate loop. A pixel
//! shows a map plate where its ray meets the plate's square nearer than what the origin
//! scene shows there (origin plate, wall or seabed); plates are drawn far to near, so
//! the nearer of two overlapping plates wins (map plates do not cut through each other).
//! A map of one has no plates here and renders exactly as before.

use nalgebra::{Point3, Vector3};

use super::{
    fill_cell_table, form, plate_footprint, CameraModel, FrameCtx, PixelConsts, PlaneForms,
    PlaneGeo, GRID, PLATE, SEABED, WALL,
};
use crate::camera::kernels::{plate_run, CellRows, PlateRun, Ramp};
use crate::scene::{ALBEDO_BLACK, ALBEDO_WHITE};

/// Outline samples per plate edge for the plate's pixel box.
const EDGE_SAMPLES: usize = 16;
/// Pixels added around the sampled outline (the edges bend between samples under
/// distortion; the box filter reaches half a pixel out).
const BOX_MARGIN: f64 = 3.0;

/// One map plate for one frame.
#[derive(Debug, Clone, Copy)]
struct PlateFrame {
    forms: PlaneForms,
    front: bool,
    half: f32,
    half_marker: f32,
    cell_per_m: f32,
    inv_wu: f32,
    inv_wv: f32,
    /// Its bordered cell table in `MapPlates::cells`, `side` cells a row.
    cells_at: usize,
    side: usize,
    rows: Option<CellRows>,
    /// Pixel box it may cover (start inclusive, end exclusive).
    x: (usize, usize),
    y: (usize, usize),
    /// Node box (inclusive) and where its light fields start in `MapPlates::fields`.
    i: (usize, usize),
    j: (usize, usize),
    fields_at: usize,
    /// Distance from the camera to the plate's centre (draw order).
    dist: f64,
}

/// The map's plates for the current frame; buffers keep their size from frame to frame.
#[derive(Default)]
pub(super) struct MapPlates {
    plates: Vec<PlateFrame>,
    cells: Vec<f32>,
    table: Vec<f32>,
    fields: Vec<[f32; 3]>,
    /// One span of plate light.
    span: [f32; GRID],
    /// Largest squared radius of a node's normalized ray (the image's field of view):
    /// outline samples beyond twice it are where the distortion polynomial stops being
    /// a projection, so the plate's box falls back to the whole image.
    max_r2: f32,
}

/// The nodes' rays and grid size, borrowed from the renderer.
pub(super) struct Nodes<'a> {
    pub(super) x: &'a [f32],
    pub(super) y: &'a [f32],
    pub(super) nx: usize,
    pub(super) width: usize,
    pub(super) height: usize,
}

impl Nodes<'_> {
    fn ny(&self) -> usize {
        self.x.len() / self.nx
    }

    /// The ray of node (i, j) lerped with the node below by `fy`.
    #[inline(always)]
    fn ray(&self, i: usize, j: usize, fy: f32) -> (f32, f32) {
        let (a, b) = (j * self.nx + i, (j + 1) * self.nx + i);
        (
            self.x[a] + (self.x[b] - self.x[a]) * fy,
            self.y[a] + (self.y[b] - self.y[a]) * fy,
        )
    }
}

/// A linear form (D, Nu or Nv) along a span from its left and right node rays.
#[inline(always)]
fn ramp(f: &[f32; 3], l: (f32, f32), r: (f32, f32)) -> Ramp {
    let a = form(f, l.0, l.1);
    Ramp {
        at: a,
        step: (form(f, r.0, r.1) - a) * (1.0 / GRID as f32),
    }
}

/// What the origin scene shows along a span (origin plate, wall, seabed), for the depth
/// test: each plane's forms from the span's first pixel.
struct Behind {
    /// The origin plate's D, Nu, Nv.
    plate: [Ramp; 3],
    wall: Ramp,
    seabed: Ramp,
    /// `h` of the origin plate, the wall and the seabed.
    h: [f32; 3],
    /// Half the origin plate's edge.
    half: f32,
    valid: [bool; 3],
}

impl Behind {
    /// Depth (along the ray, in units of its z) of what the origin scene shows at pixel
    /// `t` of the span, as `classify` picks it; infinite for open water.
    #[inline(always)]
    fn depth(&self, t: f32) -> f32 {
        let [d, u, v] = &self.plate;
        let d = d.get(t);
        let lim = self.half * d;
        if self.valid[0] && d > 1e-9 && u.get(t).abs() <= lim && v.get(t).abs() <= lim {
            return self.h[0] / d;
        }
        let at = |ok: bool, r: &Ramp, h: f32| {
            let d = r.get(t);
            if ok && d > 1e-9 {
                h / d
            } else {
                f32::INFINITY
            }
        };
        at(self.valid[1], &self.wall, self.h[1]).min(at(self.valid[2], &self.seabed, self.h[2]))
    }
}

impl MapPlates {
    pub(super) fn new(node_x: &[f32], node_y: &[f32]) -> Self {
        let max_r2 = node_x
            .iter()
            .zip(node_y)
            .fold(0f32, |m, (x, y)| m.max(x * x + y * y));
        Self {
            max_r2,
            ..Self::default()
        }
    }

    /// Place the scene's map plates for this frame: planes, boxes, cells and the light at
    /// the nodes they may cover.
    pub(super) fn prepare(&mut self, model: &CameraModel, ctx: &FrameCtx, nodes: &Nodes) {
        self.plates.clear();
        self.cells.clear();
        self.fields.clear();
        let scene = ctx.scene;
        if scene.map.is_empty() {
            return;
        }
        let t_cw = ctx.t_wc.inverse();
        let cam_w = ctx.t_wc.translation.vector;
        for plate in &scene.map {
            let t_wm = &plate.t_world_marker;
            let t_cm = t_cw * t_wm;
            let (xm, ym, zm) = (
                t_cm.rotation * Vector3::x(),
                t_cm.rotation * Vector3::y(),
                t_cm.rotation * Vector3::z(),
            );
            let om = t_cm.translation.vector;
            let nm_w = t_wm.rotation * Vector3::z();
            let front = nm_w.dot(&(cam_w - t_wm.translation.vector)) > 0.0;
            let face = if front { nm_w } else { -nm_w };
            let (geo, forms) = PlaneGeo::new(om, zm, xm, ym, face, front);
            if !forms.valid {
                // Seen edge-on.
                continue;
            }
            let half = plate.plate_half_m();
            let Some((x, y)) = self.pixel_box(model, &t_cm, half, nodes) else {
                continue;
            };
            let i = (x.0 / GRID, ((x.1 - 1) / GRID + 1).min(nodes.nx - 1));
            let j = (y.0 / GRID, ((y.1 - 1) / GRID + 1).min(nodes.ny() - 1));
            let fields_at = self.fields.len();
            for nj in j.0..=j.1 {
                for ni in i.0..=i.1 {
                    let n = nj * nodes.nx + ni;
                    let f = ctx.shade_on(&geo, nodes.x[n], nodes.y[n]);
                    self.fields.push(f);
                }
            }
            let m = &plate.marker;
            let cell_per_m = m.cells as f32 / m.size_m as f32;
            let footprint = plate_footprint(model, ctx.t_wc, t_wm, &forms);
            let side = m.cells + 2;
            fill_cell_table(&mut self.table, m);
            let cells_at = self.cells.len();
            self.cells.extend_from_slice(&self.table);
            self.plates.push(PlateFrame {
                forms,
                front,
                half: half as f32,
                half_marker: 0.5 * m.size_m as f32,
                cell_per_m,
                inv_wu: 1.0 / (footprint.0 as f32 * cell_per_m).max(1e-6),
                inv_wv: 1.0 / (footprint.1 as f32 * cell_per_m).max(1e-6),
                cells_at,
                side,
                rows: CellRows::new(&self.table, side, ALBEDO_WHITE as f32, ALBEDO_BLACK as f32),
                x,
                y,
                i,
                j,
                fields_at,
                dist: om.norm(),
            });
        }
        // Far to near: a nearer plate draws over a farther one.
        self.plates
            .sort_unstable_by(|a, b| b.dist.total_cmp(&a.dist));
    }

    /// The pixel box a plate of half edge `half` at `t_cm` may cover: its outline
    /// projected, or the whole image where the outline leaves the field the distortion
    /// model holds in (or passes behind the camera); `None` when it is off the image.
    fn pixel_box(
        &self,
        model: &CameraModel,
        t_cm: &nalgebra::Isometry3<f64>,
        half: f64,
        nodes: &Nodes,
    ) -> Option<((usize, usize), (usize, usize))> {
        let (w, h) = (nodes.width, nodes.height);
        let whole = Some(((0, w), (0, h)));
        let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
        let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)];
        for e in 0..4 {
            let (a, b) = (corners[e], corners[(e + 1) % 4]);
            for s in 0..EDGE_SAMPLES {
                let t = s as f64 / EDGE_SAMPLES as f64;
                let p = t_cm
                    * Point3::new(
                        half * (a.0 + (b.0 - a.0) * t),
                        half * (a.1 + (b.1 - a.1) * t),
                        0.0,
                    );
                if p.z <= 1e-6 {
                    return whole;
                }
                let (nx, ny) = (p.x / p.z, p.y / p.z);
                if (nx * nx + ny * ny) as f32 > 4.0 * self.max_r2 {
                    return whole;
                }
                let Some(px) = model.project(&p) else {
                    return whole;
                };
                lo = [lo[0].min(px[0]), lo[1].min(px[1])];
                hi = [hi[0].max(px[0]), hi[1].max(px[1])];
            }
        }
        let span = |lo: f64, hi: f64, n: usize| -> Option<(usize, usize)> {
            let a = (lo - BOX_MARGIN).floor().max(0.0);
            let b = (hi + BOX_MARGIN).ceil().min(n as f64);
            (a < b).then_some((a as usize, b as usize))
        };
        Some((span(lo[0], hi[0], w)?, span(lo[1], hi[1], h)?))
    }

    /// Draw the plates over row `py` of `row_mean` (electrons, before the sensor).
    pub(super) fn overlay_row(
        &mut self,
        ctx: &FrameCtx,
        pc: &PixelConsts,
        nodes: &Nodes,
        py: usize,
        row_mean: &mut [f32],
    ) {
        if self.plates.is_empty() {
            return;
        }
        let j = py / GRID;
        let fy = (py - j * GRID) as f32 * (1.0 / GRID as f32);
        let f = &ctx.forms;
        let (half_o, valid) = (pc.half, [f[PLATE].valid, f[WALL].valid, f[SEABED].valid]);
        for p in &self.plates {
            if py < p.y.0 || py >= p.y.1 {
                continue;
            }
            let cells = &self.cells[p.cells_at..p.cells_at + p.side * p.side];
            let nxb = p.i.1 - p.i.0 + 1;
            let field =
                |i: usize, j: usize| self.fields[p.fields_at + (j - p.j.0) * nxb + i - p.i.0];
            for k in p.x.0 / GRID..=(p.x.1 - 1) / GRID {
                let (xa, xb) = (p.x.0.max(k * GRID), p.x.1.min((k + 1) * GRID));
                if xa >= xb || k + 1 > p.i.1 || j + 1 > p.j.1 {
                    continue;
                }
                let (l, r) = (nodes.ray(k, j, fy), nodes.ray(k + 1, j, fy));
                let (d, nu, nv) = (
                    ramp(&p.forms.d, l, r),
                    ramp(&p.forms.u, l, r),
                    ramp(&p.forms.v, l, r),
                );
                let lerp = |a: [f32; 3], b: [f32; 3]| -> [f32; 3] {
                    std::array::from_fn(|c| a[c] + (b[c] - a[c]) * fy)
                };
                let fl = lerp(field(k, j), field(k, j + 1));
                let fr = lerp(field(k + 1, j), field(k + 1, j + 1));
                let light = |c: usize| Ramp {
                    at: fl[c],
                    step: (fr[c] - fl[c]) * (1.0 / GRID as f32),
                };
                let first = xa - k * GRID;
                let out = &mut self.span[..xb - xa];
                if p.front {
                    let run = PlateRun {
                        d,
                        nu,
                        nv,
                        half_marker: p.half_marker,
                        cell_per_m: p.cell_per_m,
                        inv_wu: p.inv_wu,
                        inv_wv: p.inv_wv,
                        cells,
                        rows: p.rows.as_ref(),
                        side: p.side as i32,
                        caustic: pc.plate_caustics,
                        ambient: light(0),
                        lamp: light(1),
                        add: light(2),
                    };
                    plate_run(pc.isa, out, first, &run);
                } else {
                    let (a, m, add) = (light(0), light(1), light(2));
                    for (t, o) in out.iter_mut().enumerate() {
                        let t = (first + t) as f32;
                        *o = pc.albedo_back * (a.get(t) + m.get(t)) + add.get(t);
                    }
                }
                let behind = Behind {
                    plate: [
                        ramp(&f[PLATE].d, l, r),
                        ramp(&f[PLATE].u, l, r),
                        ramp(&f[PLATE].v, l, r),
                    ],
                    wall: ramp(&f[WALL].d, l, r),
                    seabed: ramp(&f[SEABED].d, l, r),
                    h: [f[PLATE].h, f[WALL].h, f[SEABED].h],
                    half: half_o,
                    valid,
                };
                for (x, &o) in (xa..xb).zip(out.iter()) {
                    let t = (x - k * GRID) as f32;
                    let dd = d.get(t);
                    if dd <= 1e-9 {
                        continue;
                    }
                    let lim = p.half * dd;
                    if nu.get(t).abs() > lim || nv.get(t).abs() > lim {
                        continue;
                    }
                    if p.forms.h / dd < behind.depth(t) {
                        row_mean[x] = o;
                    }
                }
            }
        }
    }
}
