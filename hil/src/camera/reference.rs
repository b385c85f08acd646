//! The reference renderer: every pixel traced on its own in f64, undistorted by
//! iteration, shaded with the full light model. Slow and plain on purpose: the fast
//! renderer is checked against it and benchmarked beside it.

use markhold_exposure::Frame;
use nalgebra::{Isometry3, Point3, Vector3};

use super::sensor::XorShift64Star;
use super::{CameraModel, FrameInput};
use crate::scene::{MarkerSpec, Scene, Surface, WorldLamp, ALBEDO_BLACK, ALBEDO_WHITE};

/// Where a pixel's ray ends.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Hit {
    pub(crate) surface: Surface,
    pub(crate) point: Vector3<f64>,
    /// Surface normal on the side the camera sees.
    pub(crate) normal: Vector3<f64>,
    pub(crate) dist: f64,
    /// Surface coordinates, metres (marker frame x/y for plate and wall, north/east for
    /// the seabed).
    pub(crate) uv: (f64, f64),
    /// False when the plate is seen from behind.
    pub(crate) front: bool,
}

/// Distance along unit ray `r` from `o` to the plane through `p0` with normal `n`.
fn plane_hit(
    o: &Vector3<f64>,
    r: &Vector3<f64>,
    p0: &Vector3<f64>,
    n: &Vector3<f64>,
) -> Option<f64> {
    let d = n.dot(r);
    if d.abs() < 1e-12 {
        return None;
    }
    let s = n.dot(&(p0 - o)) / d;
    (s > 1e-9).then_some(s)
}

/// The world ray of pixel (u, v): origin and unit direction.
pub(crate) fn pixel_ray(
    model: &CameraModel,
    t_wc: &Isometry3<f64>,
    u: f64,
    v: f64,
) -> (Vector3<f64>, Vector3<f64>) {
    let (x, y) = model.undistort_pixel(u, v);
    let r = t_wc.rotation * Vector3::new(x, y, 1.0).normalize();
    (t_wc.translation.vector, r)
}

/// Marker-frame coordinates where the ray meets the (unbounded) plane of the plate at
/// `t_wm`.
fn plate_plane_uv(t_wm: &Isometry3<f64>, o: &Vector3<f64>, r: &Vector3<f64>) -> Option<(f64, f64)> {
    let n = t_wm.rotation * Vector3::z();
    let p0 = t_wm.translation.vector;
    let s = plane_hit(o, r, &p0, &n)?;
    let local = t_wm.inverse_transform_point(&Point3::from(o + r * s));
    Some((local.x, local.y))
}

/// Where the ray meets the square plate of half edge `half` at `t_wm`, if it does.
fn plate_hit(
    t_wm: &Isometry3<f64>,
    half: f64,
    surface: Surface,
    o: &Vector3<f64>,
    r: &Vector3<f64>,
) -> Option<Hit> {
    let nm = t_wm.rotation * Vector3::z();
    let om = t_wm.translation.vector;
    let front = nm.dot(&(o - om)) > 0.0;
    let s = plane_hit(o, r, &om, &nm)?;
    let p = o + r * s;
    let local = t_wm.inverse_transform_point(&Point3::from(p));
    (local.x.abs() <= half && local.y.abs() <= half).then_some(Hit {
        surface,
        point: p,
        normal: if front { nm } else { -nm },
        dist: s,
        uv: (local.x, local.y),
        front,
    })
}

/// Trace one ray through the scene: the nearest of the map's plates and what the origin
/// plate, the wall and the seabed show.
pub(crate) fn trace(scene: &Scene, o: &Vector3<f64>, r: &Vector3<f64>) -> Option<Hit> {
    let base = trace_origin(scene, o, r);
    let mut best: Option<Hit> = None;
    for (k, plate) in scene.map.iter().enumerate() {
        let hit = plate_hit(
            &plate.t_world_marker,
            plate.plate_half_m(),
            Surface::MapPlate(k),
            o,
            r,
        );
        if let Some(h) = hit.filter(|h| best.is_none_or(|b| h.dist < b.dist)) {
            best = Some(h);
        }
    }
    match (best, base) {
        (Some(m), Some(b)) if m.dist < b.dist => Some(m),
        (Some(m), None) => Some(m),
        (_, b) => b,
    }
}

/// Trace one ray through the origin plate, the wall and the seabed.
fn trace_origin(scene: &Scene, o: &Vector3<f64>, r: &Vector3<f64>) -> Option<Hit> {
    let t_wm = scene.t_world_marker();
    let nm = t_wm.rotation * Vector3::z();
    let om = t_wm.translation.vector;
    if let Some(hit) = plate_hit(t_wm, scene.plate_half_m(), Surface::Plate, o, r) {
        return Some(hit);
    }
    let bg = &scene.background;
    let wall_p0 = om - nm * bg.wall_behind_marker_m;
    let wall = plane_hit(o, r, &wall_p0, &nm);
    let seabed_z = om.z + bg.seabed_below_marker_m;
    let up = Vector3::new(0.0, 0.0, -1.0);
    let seabed = plane_hit(o, r, &Vector3::new(0.0, 0.0, seabed_z), &up);
    let use_wall = match (wall, seabed) {
        (Some(w), Some(s)) => w < s,
        (Some(_), None) => true,
        (None, Some(_)) => false,
        (None, None) => return None,
    };
    if use_wall {
        let s = wall?;
        let p = o + r * s;
        let local = t_wm.inverse_transform_point(&Point3::from(p));
        let front_w = nm.dot(&(o - wall_p0)) > 0.0;
        Some(Hit {
            surface: Surface::Wall,
            point: p,
            normal: if front_w { nm } else { -nm },
            dist: s,
            uv: (local.x, local.y),
            front: front_w,
        })
    } else {
        let s = seabed?;
        let p = o + r * s;
        Some(Hit {
            surface: Surface::Seabed,
            point: p,
            normal: if o.z < seabed_z { up } else { -up },
            dist: s,
            uv: (p.x, p.y),
            front: true,
        })
    }
}

/// Plate albedo of marker `m` box-filtered over a pixel footprint of (wu, wv) metres: the
/// marker's cells seen through a pixel (anti-aliased edges, as a real lens and sensor
/// give).
pub(crate) fn plate_albedo_filtered(m: &MarkerSpec, u: f64, v: f64, wu: f64, wv: f64) -> f64 {
    let l = m.size_m;
    let n = m.cells as f64;
    let cu = (u + 0.5 * l) / l * n;
    let cv = (0.5 * l - v) / l * n;
    let (wu, wv) = ((wu / l * n).max(1e-9), (wv / l * n).max(1e-9));
    // Per axis: the nearest cell border b splits the footprint between cell b-1 and b.
    let bu = cu.round();
    let au = ((bu - cu) / wu + 0.5).clamp(0.0, 1.0);
    let bv = cv.round();
    let av = ((bv - cv) / wv + 0.5).clamp(0.0, 1.0);
    let cell = |i: f64, j: f64| -> f64 {
        if i < 0.0 || j < 0.0 || i >= n || j >= n {
            return ALBEDO_WHITE;
        }
        if m.white[j as usize * m.cells + i as usize] {
            ALBEDO_WHITE
        } else {
            ALBEDO_BLACK
        }
    };
    au * (av * cell(bu - 1.0, bv - 1.0) + (1.0 - av) * cell(bu - 1.0, bv))
        + (1.0 - au) * (av * cell(bu, bv - 1.0) + (1.0 - av) * cell(bu, bv))
}

/// Scene light arriving at pixel (u, v), exitance-equivalent W/m2.
pub(crate) fn pixel_light(
    model: &CameraModel,
    scene: &Scene,
    t_wc: &Isometry3<f64>,
    lamps: &[WorldLamp],
    time_s: f64,
    u: f64,
    v: f64,
) -> f64 {
    let (o, r) = pixel_ray(model, t_wc, u, v);
    let Some(hit) = trace(scene, &o, &r) else {
        return scene.backscatter(&o, &r, f64::INFINITY, lamps);
    };
    let plate = match hit.surface {
        Surface::Plate => Some((scene.t_world_marker(), scene.marker())),
        Surface::MapPlate(k) => scene.map.get(k).map(|p| (&p.t_world_marker, &p.marker)),
        Surface::Wall | Surface::Seabed => None,
    };
    let glossy = plate.is_some() && hit.front;
    let shade = scene.shade(&hit.point, &hit.normal, &o, &r, hit.dist, lamps, glossy);
    let albedo = match plate {
        Some((t_wm, marker)) if hit.front => {
            // Footprint from the neighbouring pixels' rays on the plate plane.
            let (ox, rx) = pixel_ray(model, t_wc, u + 1.0, v);
            let (oy, ry) = pixel_ray(model, t_wc, u, v + 1.0);
            match (
                plate_plane_uv(t_wm, &ox, &rx),
                plate_plane_uv(t_wm, &oy, &ry),
            ) {
                (Some(px), Some(py)) => {
                    let wu = (px.0 - hit.uv.0).abs() + (py.0 - hit.uv.0).abs();
                    let wv = (px.1 - hit.uv.1).abs() + (py.1 - hit.uv.1).abs();
                    plate_albedo_filtered(marker, hit.uv.0, hit.uv.1, wu, wv)
                }
                _ => marker.albedo(hit.uv.0, hit.uv.1),
            }
        }
        Some(_) => scene.plate_back_albedo(),
        None => scene.rock_albedo(hit.uv.0, hit.uv.1),
    };
    let caustic = scene.caustic(hit.uv.0, hit.uv.1, time_s);
    albedo * (shade.ambient * caustic + shade.lamp) + shade.glare + shade.backscatter
}

pub(crate) fn render(input: &FrameInput, rng: &mut XorShift64Star, out: &mut Frame) {
    let FrameInput {
        model,
        scene,
        t_wc,
        lamps,
        time_s,
        e_per_unit,
        tables,
    } = *input;
    let w = model.width as usize;
    let mask = tables.gauss_mask();
    for (y, row) in out.data.chunks_exact_mut(w).enumerate() {
        for (x, px) in row.iter_mut().enumerate() {
            let light = pixel_light(model, scene, t_wc, lamps, time_s, x as f64, y as f64);
            let g = tables.half_gauss[(rng.next_u64() >> 32) as usize & mask];
            *px = tables.grey((light * e_per_unit) as f32, g);
        }
    }
}
