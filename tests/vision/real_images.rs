//! Real photographs with known geometry (`tests/fixtures/real/`): the marker corners
//! markhold's edge fit finds, against where the board's geometry and the published
//! calibration put them, compared with OpenCV's own refined corners on the same markers.
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use markhold_vision::calibration::board::{read_image, BoardDetector, GridMarker, Target};
use markhold_vision::{CameraCalibration, MarkerFamily};
use opencv::{aruco, calib3d, core, imgcodecs, prelude::*};

fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

/// The tutorial's board: 5x7 squares of 40 mm, markers of 20 mm, DICT_6X6_250.
const CHARUCO: Target = Target::Charuco {
    squares_x: 5,
    squares_y: 7,
    square_m: 0.04,
    marker_m: 0.02,
    family: MarkerFamily::Aruco6x6_250,
};

/// Each marker's four corners on the board (OpenCV's `CharucoBoard`, corner order as
/// `detectMarkers` returns them), by id.
fn board_markers() -> HashMap<i32, [core::Point3f; 4]> {
    let dict =
        aruco::get_predefined_dictionary(aruco::PREDEFINED_DICTIONARY_NAME::DICT_6X6_250).unwrap();
    let board = aruco::CharucoBoard::create(5, 7, 0.04, 0.02, &dict).unwrap();
    board
        .obj_points()
        .iter()
        .zip(board.ids().iter())
        .map(|(q, id)| {
            let mut c = [core::Point3f::default(); 4];
            for (k, p) in q.iter().enumerate() {
                c[k] = p;
            }
            (id, c)
        })
        .collect()
}

fn camera_matrix(c: &CameraCalibration) -> (core::Mat, core::Mat) {
    (
        core::Mat::from_slice_2d(&[[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]]).unwrap(),
        core::Mat::from_slice(&c.dist).unwrap().try_clone().unwrap(),
    )
}

/// Where the board's geometry puts each marker corner in `image`: the board's pose
/// from its ChArUco checker corners (saddle points, many and well spread) with the
/// published calibration, then every marker corner projected. Also the checker
/// corners' RMS residual under that pose (how good the reference is).
fn reference(
    image: &Path,
    calib: &CameraCalibration,
    board: &HashMap<i32, [core::Point3f; 4]>,
) -> (HashMap<i32, [core::Point2f; 4]>, f64) {
    let frame = read_image(image).unwrap();
    let mut det = BoardDetector::new(&CHARUCO).unwrap();
    let found = det.detect(&frame, Some(calib)).unwrap();
    let obj: core::Vector<core::Point3f> = found
        .points
        .iter()
        .map(|(x, _)| core::Point3f::new(x.x as f32, x.y as f32, x.z as f32))
        .collect();
    let img: core::Vector<core::Point2f> = found
        .points
        .iter()
        .map(|(_, p)| core::Point2f::new(p.x as f32, p.y as f32))
        .collect();
    let (k, d) = camera_matrix(calib);
    let (mut rv, mut tv) = (core::Mat::default(), core::Mat::default());
    assert!(calib3d::solve_pnp(
        &obj,
        &img,
        &k,
        &d,
        &mut rv,
        &mut tv,
        false,
        calib3d::SOLVEPNP_ITERATIVE
    )
    .unwrap());
    let mut back = core::Vector::<core::Point2f>::new();
    calib3d::project_points(
        &obj,
        &rv,
        &tv,
        &k,
        &d,
        &mut back,
        &mut core::no_array(),
        0.0,
    )
    .unwrap();
    let ss: f64 = back
        .iter()
        .zip(img.iter())
        .map(|(a, b)| f64::from((a.x - b.x).powi(2) + (a.y - b.y).powi(2)))
        .sum();
    let checker_rms = (ss / img.len() as f64).sqrt();
    let mut out = HashMap::new();
    for (id, q) in board {
        let o: core::Vector<core::Point3f> = q.iter().copied().collect();
        let mut p = core::Vector::<core::Point2f>::new();
        calib3d::project_points(&o, &rv, &tv, &k, &d, &mut p, &mut core::no_array(), 0.0).unwrap();
        out.insert(
            *id,
            [
                p.get(0).unwrap(),
                p.get(1).unwrap(),
                p.get(2).unwrap(),
                p.get(3).unwrap(),
            ],
        );
    }
    (out, checker_rms)
}

/// markhold's marker corners: the board's markers as a marker target, each marker's
/// four corners fitted by markhold's edge fit (the loop's) with the calibration in
/// hand. By id, in `detectMarkers`' order.
fn markhold_corners(
    image: &Path,
    calib: &CameraCalibration,
    board: &HashMap<i32, [core::Point3f; 4]>,
) -> HashMap<i32, [core::Point2f; 4]> {
    let markers: Vec<GridMarker> = board
        .iter()
        .map(|(id, q)| GridMarker {
            id: *id as u32,
            size_m: 0.02,
            centre_m: [
                q.iter().map(|p| f64::from(p.x)).sum::<f64>() / 4.0,
                q.iter().map(|p| f64::from(p.y)).sum::<f64>() / 4.0,
            ],
            turn_deg: 0.0,
        })
        .collect();
    let target = Target::Markers {
        family: MarkerFamily::Aruco6x6_250,
        markers: markers.clone(),
    };
    let frame = read_image(image).unwrap();
    let mut det = BoardDetector::new(&target).unwrap();
    let found = det.detect(&frame, Some(calib)).unwrap();
    // Four points per marker, in the order of its corners; the marker by its centre.
    let mut out = HashMap::new();
    for quad in found.points.chunks(4) {
        let cx = quad.iter().map(|(x, _)| x.x).sum::<f64>() / 4.0;
        let cy = quad.iter().map(|(x, _)| x.y).sum::<f64>() / 4.0;
        let m = markers
            .iter()
            .min_by(|a, b| {
                let da = (a.centre_m[0] - cx).hypot(a.centre_m[1] - cy);
                let db = (b.centre_m[0] - cx).hypot(b.centre_m[1] - cy);
                da.total_cmp(&db)
            })
            .unwrap();
        let mut c = [core::Point2f::default(); 4];
        for (k, (_, p)) in quad.iter().enumerate() {
            c[k] = core::Point2f::new(p.x as f32, p.y as f32);
        }
        out.insert(m.id as i32, c);
    }
    out
}

/// OpenCV 4.6's marker corners with its own refinement (`method`).
fn opencv_corners(
    image: &Path,
    method: aruco::CornerRefineMethod,
) -> HashMap<i32, [core::Point2f; 4]> {
    let dict =
        aruco::get_predefined_dictionary(aruco::PREDEFINED_DICTIONARY_NAME::DICT_6X6_250).unwrap();
    let mut params = aruco::DetectorParameters::create().unwrap();
    // As the tutorial's calibration sample detects these photographs.
    params.set_polygonal_approx_accuracy_rate(0.05);
    params.set_corner_refinement_method(method as i32);
    let img = imgcodecs::imread(image.to_str().unwrap(), imgcodecs::IMREAD_GRAYSCALE).unwrap();
    let (mut c, mut ids, mut rej) = (
        core::Vector::<core::Vector<core::Point2f>>::new(),
        core::Vector::<i32>::new(),
        core::Vector::<core::Vector<core::Point2f>>::new(),
    );
    aruco::detect_markers(&img, &dict, &mut c, &mut ids, &params, &mut rej).unwrap();
    c.iter()
        .zip(ids.iter())
        .map(|(q, id)| {
            (
                id,
                [
                    q.get(0).unwrap(),
                    q.get(1).unwrap(),
                    q.get(2).unwrap(),
                    q.get(3).unwrap(),
                ],
            )
        })
        .collect()
}

/// Each corner's distance from the reference, once the image's mean offset of `found`
/// from it is taken away; and that offset. A constant offset is a pixel convention (or
/// the reference's own: `cornerSubPix` reads a pixel-aligned saddle half a pixel off,
/// `tests/vision/calibrate.rs`) that the principal point absorbs; the scatter is the error.
fn errors(
    found: &HashMap<i32, [core::Point2f; 4]>,
    truth: &HashMap<i32, [core::Point2f; 4]>,
    ids: &[i32],
) -> (Vec<f64>, [f64; 2]) {
    let d: Vec<[f64; 2]> = ids
        .iter()
        .flat_map(|id| {
            let (f, t) = (found[id], truth[id]);
            (0..4).map(move |k| [f64::from(f[k].x - t[k].x), f64::from(f[k].y - t[k].y)])
        })
        .collect();
    let n = d.len() as f64;
    let mean = [
        d.iter().map(|v| v[0]).sum::<f64>() / n,
        d.iter().map(|v| v[1]).sum::<f64>() / n,
    ];
    (
        d.iter()
            .map(|v| (v[0] - mean[0]).hypot(v[1] - mean[1]))
            .collect(),
        mean,
    )
}

fn rms(e: &[f64]) -> f64 {
    (e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64).sqrt()
}

/// On OpenCV's four ChArUco tutorial photographs, markhold's marker corners scatter no
/// more about where the board's geometry puts them (pose from the checker corners, the
/// published calibration) than OpenCV's refined corners (`cornerSubPix`: no more; its
/// AprilTag edge refinement: within 5 %), on the markers both find; and every marker
/// OpenCV finds, markhold finds. The figures are printed (`--nocapture`).
#[test]
fn marker_corners_on_the_charuco_photographs_are_no_worse_than_opencvs() {
    let dir = repo("tests/fixtures/real/opencv-charuco");
    let calib = CameraCalibration::load(&dir.join("tutorial_camera_charuco.yml")).unwrap();
    let board = board_markers();
    let (mut mine, mut subpix, mut april) = (Vec::new(), Vec::new(), Vec::new());
    let (mut found_cv, mut found_mine) = (0, 0);
    for i in 0..4 {
        let image = dir.join(format!("img_0{i}.jpg"));
        let (truth, checker_rms) = reference(&image, &calib, &board);
        assert!(
            checker_rms < 0.5,
            "{}: checker corners {checker_rms} px",
            image.display()
        );
        let m = markhold_corners(&image, &calib, &board);
        let s = opencv_corners(&image, aruco::CornerRefineMethod::CORNER_REFINE_SUBPIX);
        let a = opencv_corners(&image, aruco::CornerRefineMethod::CORNER_REFINE_APRILTAG);
        found_cv += s.len();
        found_mine += m.keys().filter(|id| s.contains_key(id)).count();
        let mut ids: Vec<i32> = m
            .keys()
            .filter(|id| s.contains_key(id) && a.contains_key(id))
            .copied()
            .collect();
        ids.sort_unstable();
        let ((em, om), (es, os), (ea, oa)) = (
            errors(&m, &truth, &ids),
            errors(&s, &truth, &ids),
            errors(&a, &truth, &ids),
        );
        eprintln!(
            "img_0{i}: {} markers; checker corners {checker_rms:.3} px; marker corners RMS \
             (offset): markhold {:.3} px ({:.2}, {:.2}), OpenCV cornerSubPix {:.3} px ({:.2}, \
             {:.2}), OpenCV AprilTag {:.3} px ({:.2}, {:.2})",
            ids.len(),
            rms(&em),
            om[0],
            om[1],
            rms(&es),
            os[0],
            os[1],
            rms(&ea),
            oa[0],
            oa[1]
        );
        mine.extend(em);
        subpix.extend(es);
        april.extend(ea);
    }
    let (m, s, a) = (rms(&mine), rms(&subpix), rms(&april));
    eprintln!(
        "all: {} corners; markhold {m:.3} px, OpenCV cornerSubPix {s:.3} px, OpenCV AprilTag \
         {a:.3} px; markers found {found_mine} of OpenCV's {found_cv}",
        mine.len()
    );
    assert!(mine.len() >= 4 * 40, "{} corners compared", mine.len());
    assert_eq!(
        found_mine, found_cv,
        "markers OpenCV finds that markhold does not"
    );
    assert!(m <= s, "markhold {m} px, OpenCV cornerSubPix {s} px");
    // AprilTag's edge refinement and markhold's edge fit both reach the reference's own
    // floor (a pose from the checker corners, the print): level within 5 %.
    assert!(
        m <= 1.05 * a,
        "markhold {m} px, OpenCV AprilTag refinement {a} px"
    );
}

/// Tags OpenCV 4.6's `detectMarkers` finds with its default parameters (36h11).
fn opencv_tag_count(img: &core::Mat) -> usize {
    let dict =
        aruco::get_predefined_dictionary(aruco::PREDEFINED_DICTIONARY_NAME::DICT_APRILTAG_36h11)
            .unwrap();
    let params = aruco::DetectorParameters::create().unwrap();
    let (mut c, mut ids, mut rej) = (
        core::Vector::<core::Vector<core::Point2f>>::new(),
        core::Vector::<i32>::new(),
        core::Vector::<core::Vector<core::Point2f>>::new(),
    );
    aruco::detect_markers(img, &dict, &mut c, &mut ids, &params, &mut rej).unwrap();
    ids.len()
}

/// AprilTag 3's detections recorded with its test images (`id, (x y) x4` per line).
fn apriltag3_detections(path: &Path) -> Vec<(u32, [[f64; 2]; 4])> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let nums: Vec<f64> = l
                .split(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-'))
                .filter(|s| !s.is_empty())
                .map(|s| s.parse().unwrap())
                .collect();
            assert_eq!(nums.len(), 9, "{l}");
            let mut q = [[0.0; 2]; 4];
            for k in 0..4 {
                q[k] = [nums[1 + 2 * k], nums[2 + 2 * k]];
            }
            (nums[0] as u32, q)
        })
        .collect()
}

const SWARMATHON: [&str; 3] = [
    "33369213973_9d9bb4cc96_c",
    "34085369442_304b6bafd9_c",
    "34139872896_defdb2f8d9_c",
];

/// markhold's tags on the Swarmathon photographs against AprilTag 3's recorded
/// detections, with one detector finding and decoding them.
struct SwarmathonRun {
    /// Tags AprilTag 3's test records, and OpenCV's `detectMarkers` (defaults) finds.
    recorded: usize,
    opencv_found: usize,
    /// markhold's tags that match a recorded one (centre within 4 px), and the others.
    matched: usize,
    extra: usize,
    /// The matched corners' mean offset from the recorded ones (the pixel conventions)
    /// and their RMS scatter about it, px.
    offset: [f64; 2],
    scatter_rms: f64,
    /// Time of markhold's detection (decode and edge fit) over the three images, s.
    seconds: f64,
}

fn markhold_on_swarmathon(detector: markhold_vision::MarkerDetector) -> SwarmathonRun {
    let dir = repo("tests/fixtures/real/apriltag-swarmathon");
    let target = Target::Markers {
        family: MarkerFamily::AprilTag36h11,
        markers: vec![GridMarker {
            id: 0,
            size_m: 0.05,
            centre_m: [0.0, 0.0],
            turn_deg: 0.0,
        }],
    };
    let (mut recorded, mut matched, mut extra, mut opencv_found) = (0, 0, 0, 0);
    let mut seconds = 0.0;
    let mut d = Vec::new();
    for name in SWARMATHON {
        let frame = read_image(&dir.join(format!("{name}.jpg"))).unwrap();
        let mut det = BoardDetector::with_detector(&target, detector).unwrap();
        let t0 = std::time::Instant::now();
        let found = det.detect(&frame, None).unwrap();
        seconds += t0.elapsed().as_secs_f64();
        let mine: Vec<[[f64; 2]; 4]> = found
            .points
            .chunks(4)
            .map(|q| [0, 1, 2, 3].map(|k| [q[k].1.x, q[k].1.y]))
            .collect();
        let refs = apriltag3_detections(&dir.join(format!("{name}.txt")));
        let centre = |q: &[[f64; 2]; 4]| {
            [
                q.iter().map(|p| p[0]).sum::<f64>() / 4.0,
                q.iter().map(|p| p[1]).sum::<f64>() / 4.0,
            ]
        };
        let mut used = vec![false; mine.len()];
        let mut hits = 0;
        for (_, r) in &refs {
            let rc = centre(r);
            let Some(j) = (0..mine.len()).find(|j| {
                let c = centre(&mine[*j]);
                !used[*j] && (c[0] - rc[0]).hypot(c[1] - rc[1]) < 4.0
            }) else {
                continue;
            };
            used[j] = true;
            hits += 1;
            // The corners in the rotation (and order) that matches best.
            let m = &mine[j];
            let best = (0..4)
                .flat_map(|s| [(s, false), (s, true)])
                .map(|(s, rev)| {
                    let order: Vec<usize> = (0..4)
                        .map(|k| if rev { (s + 4 - k) % 4 } else { (s + k) % 4 })
                        .collect();
                    let e: f64 = (0..4)
                        .map(|k| {
                            (m[order[k]][0] - r[k][0]).powi(2) + (m[order[k]][1] - r[k][1]).powi(2)
                        })
                        .sum();
                    (e, order)
                })
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .unwrap()
                .1;
            for k in 0..4 {
                d.push([m[best[k]][0] - r[k][0], m[best[k]][1] - r[k][1]]);
            }
        }
        let img = imgcodecs::imread(
            dir.join(format!("{name}.jpg")).to_str().unwrap(),
            imgcodecs::IMREAD_GRAYSCALE,
        )
        .unwrap();
        let cv = opencv_tag_count(&img);
        eprintln!(
            "{name} ({}): AprilTag 3 recorded {} tags, OpenCV's detectMarkers {cv}, markhold {} \
             ({hits} of the recorded)",
            detector,
            refs.len(),
            mine.len()
        );
        opencv_found += cv;
        recorded += refs.len();
        matched += hits;
        extra += mine.len() - hits;
    }
    let n = d.len() as f64;
    let offset = [
        d.iter().map(|v| v[0]).sum::<f64>() / n,
        d.iter().map(|v| v[1]).sum::<f64>() / n,
    ];
    let scatter: Vec<f64> = d
        .iter()
        .map(|v| (v[0] - offset[0]).hypot(v[1] - offset[1]))
        .collect();
    let run = SwarmathonRun {
        recorded,
        opencv_found,
        matched,
        extra,
        offset,
        scatter_rms: rms(&scatter),
        seconds,
    };
    eprintln!(
        "all ({detector}): recorded {recorded} tags, OpenCV {opencv_found}, markhold {matched} \
         of the recorded and {extra} others; corners: offset ({:.2}, {:.2}) px, RMS about it \
         {:.3} px; {:.3} s",
        run.offset[0], run.offset[1], run.scatter_rms, run.seconds
    );
    run
}

/// The three photographs of AprilTag 3's own test suite (NASA Swarmathon robots with
/// tag36h11 id 0 on their sides, 799x533, tags 15 to 35 px across), against the
/// detections AprilTag 3 records for them (its test's settings: full resolution, no edge
/// refinement). markhold's detections with the default detector are OpenCV's quads of the
/// 36h11 dictionary with markhold's edge fit: it keeps nine in ten of OpenCV's, and on the
/// tags both find its corners agree with AprilTag 3's to well under a pixel once the
/// libraries' pixel conventions (a constant offset) are taken out. The detection rate
/// against AprilTag 3's is printed, not asserted: OpenCV's quad detector finds fewer than
/// half of these small tags (`--nocapture` prints the figures).
#[test]
fn tags_of_apriltag3s_test_photographs_against_its_own_detections() {
    let r = markhold_on_swarmathon(markhold_vision::MarkerDetector::OpenCv);
    // The edge fit keeps nine in ten of the quads OpenCV decodes (it leaves out a tag
    // whose edges it cannot fit rather than give it coarse corners).
    assert!(
        10 * (r.matched + r.extra) >= 9 * r.opencv_found,
        "markhold {} of OpenCV's {}",
        r.matched + r.extra,
        r.opencv_found
    );
    assert!(
        r.matched >= 15,
        "{} of AprilTag 3's {}",
        r.matched,
        r.recorded
    );
    assert!(r.scatter_rms < 1.0, "corners {} px apart", r.scatter_rms);
}

/// The two detectors behind markhold's edge fit on the same photographs: AprilTag 3's
/// finds at least half as many again of the recorded tags as OpenCV's, and its tags'
/// corners (markhold's edge fit either way) lie as close to the recorded corners. The
/// time ratio of one run is printed (`--nocapture`), not asserted.
#[cfg(feature = "apriltag3")]
#[test]
fn markhold_with_apriltag3_finds_more_small_tags_than_with_opencv() {
    use markhold_vision::MarkerDetector;
    let cv = markhold_on_swarmathon(MarkerDetector::OpenCv);
    let at = markhold_on_swarmathon(MarkerDetector::AprilTag3);
    eprintln!(
        "markhold with AprilTag 3: {} of {} recorded tags ({} others), corners {:.3} px; \
         with OpenCV: {} ({} others), corners {:.3} px; time with AprilTag 3 against OpenCV \
         (one run, read as a ratio): {:.2}x",
        at.matched,
        at.recorded,
        at.extra,
        at.scatter_rms,
        cv.matched,
        cv.extra,
        cv.scatter_rms,
        at.seconds / cv.seconds
    );
    assert!(
        2 * at.matched >= 3 * cv.matched,
        "AprilTag 3 {}, OpenCV {}",
        at.matched,
        cv.matched
    );
    assert!(at.scatter_rms < 1.0, "corners {} px apart", at.scatter_rms);
}

/// AprilTag 3's detections in `img` through the vision crate's detector, in AprilTag's
/// own corner order and pixel convention (as its test records them): the crate gives
/// OpenCV's order (its corner `k` is AprilTag's `(5 - k) % 4`) and convention (0.5 px
/// less).
#[cfg(feature = "apriltag3")]
fn apriltag3_detect(
    img: &core::Mat,
    decimate: f32,
    refine_edges: bool,
) -> Vec<(u32, [[f64; 2]; 4])> {
    let mut at = markhold_vision::apriltag3::AprilTag3::new(MarkerFamily::AprilTag36h11).unwrap();
    at.set_quad_decimate(decimate);
    at.set_refine_edges(refine_edges);
    let mut out = Vec::new();
    at.detect(img, |id, c| {
        let p = |j: usize| {
            let k = (5 - j) % 4;
            [f64::from(c[k][0]) + 0.5, f64::from(c[k][1]) + 0.5]
        };
        out.push((id, [p(0), p(1), p(2), p(3)]));
    })
    .unwrap();
    out
}

/// AprilTag 3 through its library on its own test photographs: with its test's settings
/// it gives the detections its test records (which checks the FFI); with its defaults
/// (half resolution, edge refinement), as a second detector beside OpenCV's, it finds
/// more of the small tags than OpenCV's `detectMarkers`. Detection counts, corner
/// agreement and the time ratio of one run are printed (`--nocapture`), not asserted.
#[cfg(feature = "apriltag3")]
#[test]
fn apriltag3_against_opencv_on_its_test_photographs() {
    let dir = repo("tests/fixtures/real/apriltag-swarmathon");
    let (mut at_full, mut at_default, mut cv, mut recorded) = (0, 0, 0, 0);
    let (mut t_at, mut t_at_full, mut t_cv) = (0.0, 0.0, 0.0);
    for name in SWARMATHON {
        let path = dir.join(format!("{name}.jpg"));
        let img = imgcodecs::imread(path.to_str().unwrap(), imgcodecs::IMREAD_GRAYSCALE).unwrap();
        let refs = apriltag3_detections(&dir.join(format!("{name}.txt")));
        // Its test's settings: the recorded detections (to 0.25 px: its test decodes the
        // JPEG with its own decoder, this one with OpenCV's, and the grey levels differ
        // by a little).
        let mut full = apriltag3_detect(&img, 1.0, false);
        full.sort_by(|a, b| {
            (a.1[0][0], a.1[0][1])
                .partial_cmp(&(b.1[0][0], b.1[0][1]))
                .unwrap()
        });
        let mut want = refs.clone();
        want.sort_by(|a, b| {
            (a.1[0][0], a.1[0][1])
                .partial_cmp(&(b.1[0][0], b.1[0][1]))
                .unwrap()
        });
        assert_eq!(full.len(), want.len(), "{name}");
        for (a, b) in full.iter().zip(&want) {
            assert_eq!(a.0, b.0);
            for k in 0..4 {
                for j in 0..2 {
                    assert!((a.1[k][j] - b.1[k][j]).abs() < 0.25, "{name}: {a:?} {b:?}");
                }
            }
        }
        // Time of each detector on the decoded image, its set-up included (AprilTag's
        // family tables, OpenCV's dictionary), one run: a ratio to read, not a test.
        let t0 = std::time::Instant::now();
        let default = apriltag3_detect(&img, 2.0, true);
        t_at += t0.elapsed().as_secs_f64();
        let t0 = std::time::Instant::now();
        apriltag3_detect(&img, 1.0, true);
        t_at_full += t0.elapsed().as_secs_f64();
        let t0 = std::time::Instant::now();
        let n_cv = opencv_tag_count(&img);
        t_cv += t0.elapsed().as_secs_f64();
        eprintln!(
            "{name}: AprilTag 3 recorded {}, full resolution {}, defaults {}; OpenCV {n_cv}",
            refs.len(),
            full.len(),
            default.len()
        );
        recorded += refs.len();
        at_full += full.len();
        at_default += default.len();
        cv += n_cv;
    }
    eprintln!(
        "all: AprilTag 3 {at_full} (recorded {recorded}), with its defaults {at_default}; \
         OpenCV's detectMarkers {cv}; time against OpenCV's: AprilTag 3 defaults {:.2}x, \
         full resolution with edge refinement {:.2}x",
        t_at / t_cv,
        t_at_full / t_cv
    );
    assert_eq!(at_full, recorded);
    assert!(at_default > cv, "AprilTag 3 {at_default}, OpenCV {cv}");
}
