//! Can the camera see the marker from the station? Where the marker's corners fall in
//! the image at the station (and on the way there from the simulator's start pose), from
//! the camera model, the mount and the station (docs/frames.md). Site loading refuses a
//! station whose marker is outside the safe region of the image; `params check` also
//! warns when the margin is thin.

use markhold_autopilot::{StationConfig, ViewLimits};
use markhold_config::ConfigError;
use markhold_vision::CameraCalibration;
use nalgebra::{Isometry3, Point3, Vector2};

/// The safe region: the image shrunk by this fraction of its width at the left and right
/// edges and of its height at the top and bottom. A station whose marker corner falls
/// outside it is refused: the detector needs the marker's white quiet zone, and the
/// vehicle's motion around the station moves the image by a few percent.
pub const REFUSE_MARGIN: f64 = 0.05;

/// A station whose nearest corner is within this fraction of an edge is accepted with a
/// warning: transients (the start, a gust) can take the marker out of view.
pub const WARN_MARGIN: f64 = 0.12;

/// Poses sampled on the straight way from the simulator's start pose to the station.
const PATH_SAMPLES: usize = 8;

/// Which image edge a corner is nearest to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Edge {
    Left,
    Right,
    Top,
    Bottom,
}

impl Edge {
    fn name(self) -> &'static str {
        match self {
            Edge::Left => "left",
            Edge::Right => "right",
            Edge::Top => "top",
            Edge::Bottom => "bottom",
        }
    }
}

/// Where the marker falls in the image for one vehicle pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerView {
    /// Corner pixels in aruco order (top-left, top-right, bottom-right, bottom-left);
    /// NaN for a corner behind the camera.
    pub corners_px: [Vector2<f64>; 4],
    /// Horizontal angle of the marker centre off the optical axis, degrees, + right.
    pub bearing_deg: f64,
    /// Vertical angle of the marker centre off the optical axis, degrees, + down.
    pub elevation_deg: f64,
    /// Camera-frame z of the marker centre, metres.
    pub range_m: f64,
    /// Smallest distance of a corner inside an image edge, as a fraction of the image's
    /// width (left, right) or height (top, bottom); negative outside the image.
    pub margin: f64,
    /// The same in pixels.
    pub margin_px: f64,
    /// The edge of that smallest margin.
    pub edge: Edge,
}

/// The half fields of view, degrees: (left, right, top, bottom) of the optical axis.
pub fn half_fov_deg(calib: &CameraCalibration) -> [f64; 4] {
    let w = f64::from(calib.width);
    let h = f64::from(calib.height);
    let l = calib.undistort_pixel(0.0, calib.cy).x;
    let r = calib.undistort_pixel(w, calib.cy).x;
    let t = calib.undistort_pixel(calib.cx, 0.0).y;
    let b = calib.undistort_pixel(calib.cx, h).y;
    [-l, r, -t, b].map(|v| v.atan().to_degrees())
}

/// The image edges as undistorted normalized coordinates (x/z, y/z), and the marker's
/// half size: what the station keeper needs to keep the marker in view.
pub fn view_limits(calib: &CameraCalibration, marker_size_m: f64) -> ViewLimits {
    let [l, r, t, b] = half_fov_deg(calib).map(|d| d.to_radians().tan());
    ViewLimits {
        left: -l,
        right: r,
        top: -t,
        bottom: b,
        marker_half_m: 0.5 * marker_size_m,
    }
}

/// Largest squared normalized radius of the image: a point beyond it is outside, even
/// where the distortion polynomial would fold it back into the image.
fn max_r2(calib: &CameraCalibration) -> f64 {
    let (w, h) = (f64::from(calib.width), f64::from(calib.height));
    [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)]
        .iter()
        .map(|&(u, v)| calib.undistort_pixel(u, v).norm_squared())
        .fold(0.0, f64::max)
}

/// Where the marker (edge `size_m`) falls in the image of a camera mounted at
/// `t_vehicle_cam` on a vehicle at `t_marker_vehicle`.
pub fn marker_view(
    calib: &CameraCalibration,
    t_vehicle_cam: &Isometry3<f64>,
    t_marker_vehicle: &Isometry3<f64>,
    size_m: f64,
) -> MarkerView {
    let t_cam_marker = (t_marker_vehicle * t_vehicle_cam).inverse();
    let (w, h) = (f64::from(calib.width), f64::from(calib.height));
    let r2_max = max_r2(calib) * 1.0001;
    let half = 0.5 * size_m;
    let mut corners_px = [Vector2::new(f64::NAN, f64::NAN); 4];
    let mut margin = f64::INFINITY;
    let mut margin_px = f64::INFINITY;
    let mut edge = Edge::Left;
    let object = [(-half, half), (half, half), (half, -half), (-half, -half)];
    for (px, (x, y)) in corners_px.iter_mut().zip(object) {
        let p = t_cam_marker * Point3::new(x, y, 0.0);
        let n = Vector2::new(p.x / p.z, p.y / p.z);
        if p.z <= 1e-6 {
            let (e, m) = behind_edge(&n);
            if m < margin {
                (margin, margin_px, edge) = (m, m * w, e);
            }
            continue;
        }
        // Beyond the image's widest ray the distortion polynomial can fold a point back
        // into the image: there the pinhole pixel (outside the image too) is used.
        let uv = if n.norm_squared() > r2_max {
            Vector2::new(calib.fx * n.x + calib.cx, calib.fy * n.y + calib.cy)
        } else {
            calib.distort_with_jacobian(n.x, n.y).0
        };
        *px = uv;
        for (e, m_px, span) in [
            (Edge::Left, uv.x, w),
            (Edge::Right, w - uv.x, w),
            (Edge::Top, uv.y, h),
            (Edge::Bottom, h - uv.y, h),
        ] {
            let m = m_px / span;
            if m < margin {
                (margin, margin_px, edge) = (m, m_px, e);
            }
        }
    }
    let c = t_cam_marker.translation.vector;
    MarkerView {
        corners_px,
        bearing_deg: c.x.atan2(c.z).to_degrees(),
        elevation_deg: c.y.atan2(c.z).to_degrees(),
        range_m: c.z,
        margin,
        margin_px,
        edge,
    }
}

/// A corner behind the camera: out of view, on the side its ray points away from.
fn behind_edge(n: &Vector2<f64>) -> (Edge, f64) {
    let (x, y) = (-n.x, -n.y);
    let e = if x.abs() >= y.abs() {
        if x < 0.0 {
            Edge::Left
        } else {
            Edge::Right
        }
    } else if y < 0.0 {
        Edge::Top
    } else {
        Edge::Bottom
    };
    (e, -1.0)
}

/// The camera-side facts a check needs: calibration, mount, marker size.
#[derive(Debug, Clone, Copy)]
pub struct ViewSetup<'a> {
    pub calib: &'a CameraCalibration,
    pub t_vehicle_cam: Isometry3<f64>,
    /// The site's `[camera] mount_rpy_deg` and `mount_position_m`, for messages.
    pub mount_rpy_deg: [f64; 3],
    pub mount_position_m: [f64; 3],
    pub marker_size_m: f64,
    /// The map's other markers (`[[marker.map]]`), placed in the site frame.
    pub others: &'a [markhold_vision::MapMarker],
}

impl ViewSetup<'_> {
    /// The view of the site from a vehicle at `t_site_vehicle`: the origin marker's,
    /// unless another marker of the map lies further inside the image (then that one's).
    pub fn view(&self, t_site_vehicle: &Isometry3<f64>) -> MarkerView {
        let origin = marker_view(
            self.calib,
            &self.t_vehicle_cam,
            t_site_vehicle,
            self.marker_size_m,
        );
        self.others.iter().fold(origin, |best, m| {
            let t_marker_vehicle = m.t_site_marker().inverse() * t_site_vehicle;
            let v = marker_view(self.calib, &self.t_vehicle_cam, &t_marker_vehicle, m.size_m);
            if v.margin > best.margin || best.margin.is_nan() && !v.margin.is_nan() {
                v
            } else {
                best
            }
        })
    }
}

/// What the check found: the view at the station, the worst view on the way from the
/// start pose (when given), and the warnings to print.
#[derive(Debug, Clone)]
pub struct Feasibility {
    pub station: MarkerView,
    /// The view at the simulator's start pose itself.
    pub at_start: Option<MarkerView>,
    pub worst_on_way: Option<MarkerView>,
    pub warnings: Vec<String>,
}

/// Rounded to a tenth, without a negative zero.
fn tenth(v: f64) -> f64 {
    (v * 10.0).round() / 10.0 + 0.0
}

fn describe(v: &MarkerView, half: &[f64; 4]) -> String {
    let side = if v.bearing_deg < 0.0 { "left" } else { "right" };
    let half_h = if v.bearing_deg < 0.0 {
        half[0]
    } else {
        half[1]
    };
    let half_v = if v.elevation_deg < 0.0 {
        half[2]
    } else {
        half[3]
    };
    format!(
        "marker centre at bearing {:.1} deg ({:.1} deg {side} of the optical axis; half field \
         of view {half_h:.1} deg), elevation {:.1} deg (half field of view {half_v:.1} deg), \
         {:.2} m ahead of the camera; nearest corner {:.0} px {} the {} edge (margin {:.1} %)",
        tenth(v.bearing_deg),
        v.bearing_deg.abs(),
        tenth(v.elevation_deg),
        v.range_m,
        v.margin_px.abs(),
        if v.margin_px < 0.0 {
            "outside"
        } else {
            "inside"
        },
        v.edge.name(),
        100.0 * v.margin
    )
}

fn station_value(st: &StationConfig, setup: &ViewSetup<'_>) -> String {
    let [r, p, y] = setup.mount_rpy_deg;
    let [x, yy, z] = setup.mount_position_m;
    format!(
        "distance_m {}, lateral_m {}, vertical_m {}, yaw_deg {} with camera.mount_rpy_deg \
         [{r}, {p}, {y}], camera.mount_position_m [{x}, {yy}, {z}]",
        st.distance_m, st.lateral_m, st.vertical_m, st.yaw_deg
    )
}

/// Checks the station (and the way from `start`, the simulator's start pose in the
/// marker frame, with the keys that place it): refused (the error names `station` and
/// the bearing and margin) when the marker at the station is outside the safe region; a
/// warning when its margin is thin, or when the marker leaves the safe region on the way
/// from the start.
pub fn check(
    setup: &ViewSetup<'_>,
    station: &StationConfig,
    start: Option<(&Isometry3<f64>, &str)>,
) -> Result<Feasibility, ConfigError> {
    let half = half_fov_deg(setup.calib);
    let goal = station.t_marker_vehicle();
    let at_station = setup.view(&goal);
    let mut warnings = Vec::new();
    // NaN (a degenerate pose) is refused too.
    if at_station.margin.is_nan() || at_station.margin < REFUSE_MARGIN {
        return Err(ConfigError::new(
            "station",
            station_value(station, setup),
            format!(
                "the marker inside the camera's safe region at the station (every corner at \
                 least {:.0} % of the image inside its edges); here the {}",
                100.0 * REFUSE_MARGIN,
                describe(&at_station, &half)
            ),
        ));
    }
    if at_station.margin < WARN_MARGIN {
        warnings.push(format!(
            "station: the marker is near the edge of the view: {} (below {:.0} %: a \
             transient can take it out of view)",
            describe(&at_station, &half),
            100.0 * WARN_MARGIN
        ));
    }
    let mut worst_on_way = None;
    let mut at_start = None;
    if let Some((t_start, keys)) = start {
        at_start = Some(setup.view(t_start));
        let worst = (0..PATH_SAMPLES)
            .map(|i| {
                let s = i as f64 / PATH_SAMPLES as f64;
                // try_slerp: half a turn apart has no single way between (slerp panics).
                let rotation = t_start
                    .rotation
                    .try_slerp(&goal.rotation, s, 1e-9)
                    .unwrap_or(t_start.rotation);
                let translation = t_start.translation.vector.lerp(&goal.translation.vector, s);
                let pose = Isometry3::from_parts(translation.into(), rotation);
                setup.view(&pose)
            })
            .fold(None::<MarkerView>, |w, v| match w {
                Some(w) if w.margin <= v.margin => Some(w),
                _ => Some(v),
            });
        if let Some(w) = worst {
            // The start pose is the simulator's: a warning, never a refusal of the site.
            if w.margin < REFUSE_MARGIN {
                let what = if w.margin < 0.0 {
                    "leaves the view"
                } else {
                    "comes near the edge of the view"
                };
                warnings.push(format!(
                    "{keys}: on the way from the simulator's start pose to the station the \
                     marker {what}: {}",
                    describe(&w, &half)
                ));
            }
            worst_on_way = Some(w);
        }
    }
    Ok(Feasibility {
        station: at_station,
        at_start,
        worst_on_way,
        warnings,
    })
}

/// The setup of a site's camera, for [`check`].
fn setup_of<'a>(site: &'a crate::params::Site, calib: &'a CameraCalibration) -> ViewSetup<'a> {
    ViewSetup {
        calib,
        t_vehicle_cam: crate::params::t_vehicle_cam(&site.camera),
        mount_rpy_deg: site.camera.mount_rpy_deg,
        mount_position_m: site.camera.mount_position_m,
        marker_size_m: site.marker.size_m,
        others: &site.marker.map,
    }
}

/// The keys that place the simulator's start pose, for messages.
const START_KEYS: &str = "vehicle.initial_offset_m, vehicle.initial_offset_deg";

/// The check of a site: its station, and (given by the simulator, in the marker frame)
/// the way from its start pose. The field never passes a start: the start pose is the
/// simulator's (`[vehicle] initial_offset_m`, `initial_offset_deg`).
pub fn check_site(
    site: &crate::params::Site,
    calib: &CameraCalibration,
    start: Option<&Isometry3<f64>>,
) -> Result<Feasibility, ConfigError> {
    check(
        &setup_of(site, calib),
        &site.station,
        start.map(|t| (t, START_KEYS)),
    )
}

/// The simulator's start: refused when the marker at the start pose is outside the safe
/// region, since a run that starts blind has nothing to hold (on a vehicle, the pilot
/// engages with the marker in view). `start_at(offset_m)` is the start pose in the marker
/// frame for an `initial_offset_m`; the error names the largest offset, at the site's
/// `initial_offset_deg`, that starts in view.
pub fn check_start(
    site: &crate::params::Site,
    calib: &CameraCalibration,
    offset_m: f64,
    offset_deg: f64,
    start_at: impl Fn(f64) -> Isometry3<f64>,
) -> Result<(), ConfigError> {
    // The simulated world draws every marker of the map: the start must see one of them.
    let setup = setup_of(site, calib);
    let margin_at = |d: f64| setup.view(&start_at(d));
    let v = margin_at(offset_m);
    if v.margin >= REFUSE_MARGIN {
        return Ok(());
    }
    // Bisection on the offset: the station itself is in the safe region (checked at
    // load), so the margin at 0 is at least REFUSE_MARGIN.
    let (mut lo, mut hi) = (0.0, offset_m);
    for _ in 0..30 {
        let mid = 0.5 * (lo + hi);
        if margin_at(mid).margin >= REFUSE_MARGIN {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Err(ConfigError::new(
        "vehicle.initial_offset_m",
        offset_m,
        format!(
            "a simulator start pose from which the camera sees the marker (every corner at \
             least {:.0} % of the image inside its edges; a run that starts blind has \
             nothing to hold); here, with vehicle.initial_offset_deg {}, the {}; an \
             initial_offset_m of at most {:.3} starts in view",
            100.0 * REFUSE_MARGIN,
            offset_deg,
            describe(&v, &half_fov_deg(calib)),
            (lo * 1000.0).floor() / 1000.0
        ),
    ))
}

/// `params check`'s lines about the view: the marker at the station, at and on the way
/// from the simulator's start pose (when given), and the warnings.
pub fn print_check(site: &crate::params::LoadedSite, start: Option<&Isometry3<f64>>) {
    // The site loaded, so the station check passed; it is repeated for its figures.
    let Ok(f) = check_site(&site.site, &site.calibration, start) else {
        return;
    };
    let half = half_fov_deg(&site.calibration);
    crate::outln!("# view at the station: {}", describe(&f.station, &half));
    if let Some(v) = &f.at_start {
        crate::outln!(
            "# view at the simulator's start pose: {}",
            describe(v, &half)
        );
        if v.margin.is_nan() || v.margin < REFUSE_MARGIN {
            crate::outln!(
                "# warning: {START_KEYS}: `markhold hil` refuses this start: the marker is \
                 outside the safe region at the simulator's start pose"
            );
        }
    }
    if let Some(w) = &f.worst_on_way {
        crate::outln!(
            "# view on the way from the simulator's start pose, worst: {}",
            describe(w, &half)
        );
    }
    for w in &f.warnings {
        crate::outln!("# warning: {w}");
    }
}

/// Logs the site's view warnings (a run starting on a thin margin; the way from the
/// simulator's start pose when given).
pub fn warn_site(site: &crate::params::LoadedSite, start: Option<&Isometry3<f64>>) {
    if let Ok(f) = check_site(&site.site, &site.calibration, start) {
        for w in &f.warnings {
            tracing::warn!("{}: {w}", site.path.display());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Translation3, UnitQuaternion};

    fn pool() -> CameraCalibration {
        CameraCalibration::pinhole(1440, 1080, 1200.0, 1200.0, 720.0, 540.0)
    }

    fn mount(yaw_deg: f64, pitch_deg: f64) -> Isometry3<f64> {
        let tilt = Rotation3::from_euler_angles(0.0, pitch_deg.to_radians(), yaw_deg.to_radians());
        let base = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(
            0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0,
        ));
        Isometry3::from_parts(
            Translation3::new(0.2, 0.0, 0.0),
            UnitQuaternion::from_rotation_matrix(&(tilt * base)),
        )
    }

    fn view(mount_yaw: f64, yaw: f64, lateral: f64) -> MarkerView {
        let st = StationConfig {
            yaw_deg: yaw,
            lateral_m: lateral,
            ..Default::default()
        };
        marker_view(
            &pool(),
            &mount(mount_yaw, 0.0),
            &st.t_marker_vehicle(),
            0.15,
        )
    }

    #[test]
    fn straight_ahead_is_centred() {
        let v = view(0.0, 0.0, 0.0);
        assert!(v.bearing_deg.abs() < 1e-9 && v.elevation_deg.abs() < 1e-9);
        // 0.15 m at 0.8 m: 225 px wide, centred: 607.5 px from the left and right edges.
        assert!((v.range_m - 0.8).abs() < 1e-9);
        assert!((v.corners_px[0].x - (720.0 - 112.5)).abs() < 1e-6, "{v:?}");
        assert!((v.corners_px[0].y - (540.0 - 112.5)).abs() < 1e-6, "{v:?}");
        assert_eq!(v.edge, Edge::Top);
        assert!((v.margin_px - 427.5).abs() < 1e-6);
    }

    #[test]
    fn mount_yaw_right_puts_the_marker_left() {
        let v = view(10.0, 0.0, 0.0);
        assert!((v.bearing_deg + 10.0).abs() < 1e-9, "{v:?}");
        // Station yaw right also puts it left, and the camera's lever arm (0.2 m ahead of
        // the centre of gravity) swings the camera right, adding to the bearing.
        let v = view(0.0, 15.0, 0.0);
        assert!(v.bearing_deg < -15.0 - 3.0, "{v:?}");
        // Mount and station yaw against each other nearly cancel.
        let v = view(10.0, -15.0, 0.0);
        assert!(v.bearing_deg > 5.0 && v.bearing_deg < 10.0, "{v:?}");
    }

    #[test]
    fn offsets_that_add_put_a_corner_outside() {
        for (m, y, l) in [(10.0, 15.0, 0.0), (10.0, 0.0, 0.3), (0.0, 15.0, 0.3)] {
            let v = view(m, y, l);
            assert!(v.margin < 0.0 && v.edge == Edge::Left, "{m} {y} {l}: {v:?}");
        }
    }

    #[test]
    fn a_start_half_a_turn_away_is_checked_without_a_panic() {
        let setup = ViewSetup {
            calib: &pool(),
            t_vehicle_cam: mount(0.0, 0.0),
            mount_rpy_deg: [0.0; 3],
            mount_position_m: [0.2, 0.0, 0.0],
            marker_size_m: 0.15,
            others: &[],
        };
        let st = StationConfig::default();
        let turned = st.t_marker_vehicle()
            * Isometry3::rotation(nalgebra::Vector3::z() * std::f64::consts::PI);
        let f = check(&setup, &st, Some((&turned, START_KEYS))).unwrap();
        assert!(f.worst_on_way.unwrap().margin < 0.0);
        assert!(
            f.warnings.iter().any(|w| w.contains("leaves the view")),
            "{:?}",
            f.warnings
        );
    }

    #[test]
    fn a_blind_start_is_refused_with_an_offset_that_sees() {
        let mut site: crate::params::Site =
            toml::from_str(include_str!("../../params/pool.toml")).unwrap();
        site.camera.mount_rpy_deg = [0.0, -10.0, 0.0];
        let calib = pool();
        // Straight below the station: the marker rises out of the top of the image.
        let start_at =
            |d: f64| site.station.t_marker_vehicle() * Isometry3::translation(0.0, 0.0, d);
        let e = check_start(&site, &calib, 0.5, 0.0, start_at).unwrap_err();
        assert_eq!(e.key, "vehicle.initial_offset_m");
        let at_most: f64 = e
            .expected
            .split("at most ")
            .nth(1)
            .and_then(|t| t.split_whitespace().next())
            .unwrap()
            .parse()
            .unwrap();
        assert!(at_most > 0.0 && at_most < 0.5, "{e}");
        assert!(check_start(&site, &calib, at_most, 0.0, start_at).is_ok());
        assert!(check_start(&site, &calib, at_most + 0.01, 0.0, start_at).is_err());
    }

    /// A station in front of a marker of the map, with the origin marker out of view:
    /// refused for the origin alone, accepted with the map.
    #[test]
    fn a_station_in_front_of_another_marker_of_the_map_is_accepted() {
        let calib = pool();
        let others = [markhold_vision::MapMarker {
            id: 1,
            size_m: 0.15,
            position_m: [1.5, 0.0, 0.0],
            rpy_deg: [0.0; 3],
            plane: None,
        }];
        let setup = ViewSetup {
            calib: &calib,
            t_vehicle_cam: mount(0.0, 0.0),
            mount_rpy_deg: [0.0; 3],
            mount_position_m: [0.2, 0.0, 0.0],
            marker_size_m: 0.15,
            others: &others,
        };
        let st = StationConfig {
            lateral_m: 1.5,
            ..StationConfig::default()
        };
        let f = check(&setup, &st, None).unwrap();
        assert!(f.station.margin > 0.3, "{:?}", f.station);
        let alone = ViewSetup {
            others: &[],
            ..setup
        };
        let e = check(&alone, &st, None).unwrap_err();
        assert_eq!(e.key, "station");
    }

    #[test]
    fn behind_the_camera_is_outside() {
        let v = view(180.0, 0.0, 0.0);
        assert!(v.margin < 0.0, "{v:?}");
    }

    #[test]
    fn limits_are_the_half_fields_of_view() {
        let l = view_limits(&pool(), 0.15);
        assert!((l.right - 0.6).abs() < 1e-9 && (l.left + 0.6).abs() < 1e-9);
        assert!((l.bottom - 0.45).abs() < 1e-9 && (l.top + 0.45).abs() < 1e-9);
        let fov = half_fov_deg(&pool());
        assert!((fov[0] - 30.96).abs() < 0.01, "{fov:?}");
    }
}
