//! A reference renderer of a printed marker seen by a calibrated camera, for tests,
//! benches and parity checks: every pixel is the area average of `supersample^2`
//! rays cast through the (distorted) camera onto the marker plane. No noise: callers
//! add their own.

use crate::{CameraCalibration, MarkerBitmap};
use markhold_camera::Frame;
use nalgebra::{Isometry3, Point3, Vector3};

/// Grey levels and geometry of the scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneParams {
    /// Grey level of black modules.
    pub black: f64,
    /// Grey level of white modules and of the paper around the marker.
    pub white: f64,
    /// Grey level of everything beyond the paper.
    pub background: f64,
    /// White paper around the black border, in modules, each side.
    pub margin_cells: f64,
    /// Rays per pixel side (area anti-aliasing); edges are placed to 1/supersample^2
    /// px.
    pub supersample: u32,
}

impl Default for SceneParams {
    fn default() -> Self {
        Self {
            black: 30.0,
            white: 200.0,
            background: 90.0,
            margin_cells: 1.5,
            supersample: 6,
        }
    }
}

/// Render `bitmap` (side `size_m` for the black square) at `t_cam_marker` into
/// `frame` (resized to the calibration's resolution). Returns the exact pixel
/// positions of the four corners in aruco order (`None` for a corner behind the
/// camera).
pub fn render_marker(
    frame: &mut Frame,
    calib: &CameraCalibration,
    bitmap: &MarkerBitmap,
    size_m: f64,
    t_cam_marker: &Isometry3<f64>,
    scene: &SceneParams,
) -> [Option<[f64; 2]>; 4] {
    clear(frame, calib, scene);
    draw_marker(frame, calib, (bitmap, size_m, t_cam_marker), scene)
}

/// Several markers in one frame (a marker map): the background, then each marker on its
/// paper; returns each marker's exact corners as [`render_marker`] does. Papers that
/// overlap in the image are drawn in the given order.
pub fn render_markers(
    frame: &mut Frame,
    calib: &CameraCalibration,
    markers: &[(&MarkerBitmap, f64, Isometry3<f64>)],
    scene: &SceneParams,
) -> Vec<[Option<[f64; 2]>; 4]> {
    clear(frame, calib, scene);
    markers
        .iter()
        .map(|(bitmap, size_m, t)| draw_marker(frame, calib, (bitmap, *size_m, t), scene))
        .collect()
}

/// `frame` at the calibration's resolution, every pixel the scene's background.
fn clear(frame: &mut Frame, calib: &CameraCalibration, scene: &SceneParams) {
    frame.resize(calib.width, calib.height);
    let bg = scene.background.round().clamp(0.0, 255.0) as u8;
    frame.data.fill(bg);
}

/// One marker (its bitmap, side and pose, as [`render_marker`] takes them) over what
/// `frame` holds: pixels that see only the background beyond its paper are left as
/// they are.
fn draw_marker(
    frame: &mut Frame,
    calib: &CameraCalibration,
    (bitmap, size_m, t_cam_marker): (&MarkerBitmap, f64, &Isometry3<f64>),
    scene: &SceneParams,
) -> [Option<[f64; 2]>; 4] {
    let cells = bitmap.cells as f64;
    let cell_m = size_m / cells;
    let half_paper = size_m / 2.0 + scene.margin_cells * cell_m;
    let t_marker_cam = t_cam_marker.inverse();
    let origin = t_marker_cam.translation.vector;

    // Bounding box of the paper in the image (sampled along its edges: distortion
    // bends them), padded by a few pixels.
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    let n = 32;
    for i in 0..=n {
        let s = -half_paper + 2.0 * half_paper * i as f64 / n as f64;
        for (x, y) in [
            (s, half_paper),
            (s, -half_paper),
            (half_paper, s),
            (-half_paper, s),
        ] {
            if let Some(uv) = calib.project(&(t_cam_marker * Point3::new(x, y, 0.0))) {
                x0 = x0.min(uv.x);
                y0 = y0.min(uv.y);
                x1 = x1.max(uv.x);
                y1 = y1.max(uv.y);
            } else {
                // Part of the paper is behind the camera: render every pixel.
                (x0, y0, x1, y1) = (0.0, 0.0, calib.width as f64, calib.height as f64);
            }
        }
    }
    let w = calib.width as usize;
    let px0 = (x0 - 3.0).floor().clamp(0.0, calib.width as f64) as usize;
    let py0 = (y0 - 3.0).floor().clamp(0.0, calib.height as f64) as usize;
    let px1 = (x1 + 3.0).ceil().clamp(0.0, calib.width as f64) as usize;
    let py1 = (y1 + 3.0).ceil().clamp(0.0, calib.height as f64) as usize;

    let ss = scene.supersample.max(1);
    let inv = 1.0 / (ss * ss) as f64;
    let rot = t_marker_cam.rotation;
    let geo = Geometry {
        size_m,
        half_paper,
        cell_m,
        cells: bitmap.cells,
    };
    // Marker-plane point hit by the ray through pixel position (u, v).
    let hit = |u: f64, v: f64| -> Option<(f64, f64)> {
        let n = calib.undistort_pixel(u, v);
        let d = rot * Vector3::new(n.x, n.y, 1.0);
        if d.z.abs() < 1e-12 {
            return None;
        }
        let lambda = -origin.z / d.z;
        (lambda > 0.0).then(|| (origin.x + lambda * d.x, origin.y + lambda * d.y))
    };
    let region_at =
        |u: f64, v: f64| hit(u, v).map_or(Region::Background(9), |(x, y)| geo.region(x, y));
    // Regions of the pixel corners of two consecutive rows: a pixel whose four corners
    // fall in the same convex region is uniform and needs no rays.
    let ncols = px1.saturating_sub(px0) + 1;
    let mut top: Vec<Region> = (0..ncols)
        .map(|i| region_at((px0 + i) as f64 - 0.5, py0 as f64 - 0.5))
        .collect();
    let mut bottom = vec![Region::Background(9); ncols];
    for py in py0..py1 {
        for (i, r) in bottom.iter_mut().enumerate() {
            *r = region_at((px0 + i) as f64 - 0.5, py as f64 + 0.5);
        }
        for px in px0..px1 {
            let i = px - px0;
            let r = top[i];
            let uniform = r == top[i + 1] && r == bottom[i] && r == bottom[i + 1];
            if uniform && matches!(r, Region::Background(_)) {
                continue;
            }
            let value = if uniform {
                r.shade(bitmap, scene)
            } else {
                let mut acc = 0.0;
                for sy in 0..ss {
                    for sx in 0..ss {
                        // Pixel centres are at integer coordinates (OpenCV convention).
                        // Sheared grid: all ss^2 rays have distinct x and distinct y,
                        // so an axis-aligned edge is placed to 1/ss^2 px, not 1/ss.
                        let ox = (sx as f64 + (sy as f64 + 0.5) / ss as f64) / ss as f64;
                        let oy = (sy as f64 + (sx as f64 + 0.5) / ss as f64) / ss as f64;
                        acc += region_at(px as f64 - 0.5 + ox, py as f64 - 0.5 + oy)
                            .shade(bitmap, scene);
                    }
                }
                acc * inv
            };
            frame.data[py * w + px] = value.round().clamp(0.0, 255.0) as u8;
        }
        std::mem::swap(&mut top, &mut bottom);
    }
    crate::pose::marker_object_points(size_m)
        .map(|p| calib.project(&(t_cam_marker * p)).map(|uv| [uv.x, uv.y]))
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Region {
    /// Beyond the paper, with its sector around the paper (8 convex pieces; 9 = the
    /// ray misses the plane).
    Background(u8),
    /// The white paper around the marker, with its sector (8 convex pieces).
    Paper(u8),
    /// Module (row, col), top-left first.
    Cell(usize, usize),
}

impl Region {
    fn shade(self, bitmap: &MarkerBitmap, scene: &SceneParams) -> f64 {
        match self {
            Region::Background(_) => scene.background,
            Region::Paper(_) => scene.white,
            Region::Cell(r, c) if bitmap.is_white(r, c) => scene.white,
            Region::Cell(..) => scene.black,
        }
    }
}

struct Geometry {
    size_m: f64,
    half_paper: f64,
    cell_m: f64,
    cells: usize,
}

impl Geometry {
    fn region(&self, x: f64, y: f64) -> Region {
        // Sector of the 3x3 partition around a centred square of half-side `a`.
        let sector = |a: f64| {
            let s = |v: f64| {
                if v < -a {
                    0u8
                } else if v > a {
                    2
                } else {
                    1
                }
            };
            3 * s(y) + s(x)
        };
        if x.abs() > self.half_paper || y.abs() > self.half_paper {
            return Region::Background(sector(self.half_paper));
        }
        let h = self.size_m / 2.0;
        if x.abs() >= h || y.abs() >= h {
            return Region::Paper(sector(h));
        }
        // Column from the left edge, row from the top edge (marker y is up).
        let col = (((x + h) / self.cell_m).floor() as usize).min(self.cells - 1);
        let row = (((h - y) / self.cell_m).floor() as usize).min(self.cells - 1);
        Region::Cell(row, col)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{marker_bitmap, MarkerFamily};

    #[test]
    fn frontal_marker_has_black_border_where_projected() {
        let calib = CameraCalibration::pinhole(320, 240, 300.0, 300.0, 160.0, 120.0);
        let bm = marker_bitmap(MarkerFamily::AprilTag36h11, 3).unwrap();
        let mut f = Frame::default();
        // Facing the camera: marker y up (camera -y), marker z toward the camera.
        let pose = Isometry3::new(Vector3::z(), Vector3::x() * std::f64::consts::PI);
        let c = render_marker(&mut f, &calib, &bm, 0.2, &pose, &SceneParams::default());
        // 0.2 m at 1 m and f = 300: 60 px square centred on (160, 120).
        let tl = c[0].unwrap();
        assert!(
            (tl[0] - 130.0).abs() < 1e-9 && (tl[1] - 90.0).abs() < 1e-9,
            "{tl:?}"
        );
        let br = c[2].unwrap();
        assert!(
            (br[0] - 190.0).abs() < 1e-9 && (br[1] - 150.0).abs() < 1e-9,
            "{br:?}"
        );
        let at = |x: usize, y: usize| f.data[y * 320 + x];
        assert_eq!(at(132, 120), 30, "left border is black");
        assert_eq!(at(127, 120), 200, "paper is white");
        assert_eq!(at(10, 10), 90, "background");
        // Half-covered pixel on the edge x = 130 (pixel 130 spans 129.5..130.5).
        assert_eq!(at(130, 100), 115);
    }
}
