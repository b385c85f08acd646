//! Markers declared on one plane (`plane = "wall"` in `[marker]` and `[[marker.map]]`):
//! how far the map puts them off a common plane, and how that compares with what its
//! covariance says. A flat wall that comes out bent is model error the corners alone
//! may not show (a wrong focal length bends a map of one wall).

use nalgebra::{Isometry3, Matrix3, Matrix6, Point3, Vector3};

/// The coplanarity of one named plane's markers.
#[derive(Debug, Clone, PartialEq)]
pub struct PlaneReport {
    pub name: String,
    pub ids: Vec<u32>,
    /// Distances of every marker corner from the plane fitted to all of them: RMS and
    /// largest, metres, and the marker with the largest.
    pub rms_m: f64,
    pub max_m: f64,
    pub worst_id: u32,
    /// The largest angle between a marker's face and the plane, degrees, and its marker.
    pub max_tilt_deg: f64,
    pub tilt_id: u32,
    /// The largest distance of a marker centre from the plane over its standard
    /// deviation along the plane's normal (from the map's covariance before the planes
    /// scaled it).
    pub max_sigmas: f64,
}

/// Check each named plane with two markers or more; returns the reports and the
/// factor by which the covariance understates the out-of-plane deviations (mean of the
/// squared deviation-to-sigma ratios over the redundant markers of planes of four or
/// more markers; 1 without such a plane).
pub(super) fn check(
    planes: &[Option<String>],
    markers: &[(u32, f64)],
    t_site: &[Isometry3<f64>],
    obj: &[[Point3<f64>; 4]],
    covs: &[Matrix6<f64>],
) -> (Vec<PlaneReport>, f64) {
    let mut names: Vec<&str> = planes.iter().flatten().map(String::as_str).collect();
    names.sort_unstable();
    names.dedup();
    let (mut reports, mut chi2, mut dof) = (Vec::new(), 0.0, 0usize);
    for name in names {
        let members: Vec<usize> = (0..planes.len())
            .filter(|m| planes[*m].as_deref() == Some(name))
            .collect();
        if members.len() < 2 {
            continue;
        }
        let corners: Vec<(usize, Vector3<f64>)> = members
            .iter()
            .flat_map(|m| obj[*m].iter().map(move |p| (*m, (t_site[*m] * p).coords)))
            .collect();
        let centroid =
            corners.iter().fold(Vector3::zeros(), |a, (_, p)| a + p) / corners.len() as f64;
        let mut scatter = Matrix3::zeros();
        for (_, p) in &corners {
            let d = p - centroid;
            scatter += d * d.transpose();
        }
        let eig = scatter.symmetric_eigen();
        let k = (0..3)
            .min_by(|a, b| eig.eigenvalues[*a].total_cmp(&eig.eigenvalues[*b]))
            .unwrap_or(2);
        let n: Vector3<f64> = eig.eigenvectors.column(k).into();
        let (mut sum2, mut max, mut worst) = (0.0, 0.0_f64, members[0]);
        for (m, p) in &corners {
            let d = (p - centroid).dot(&n);
            sum2 += d * d;
            if d.abs() > max {
                max = d.abs();
                worst = *m;
            }
        }
        let (mut max_tilt, mut tilt_id, mut max_sigmas) = (0.0_f64, members[0], 0.0_f64);
        let mut ratios = Vec::new();
        for m in &members {
            let face = t_site[*m].rotation * Vector3::z();
            let tilt = face.dot(&n).abs().min(1.0).acos().to_degrees();
            if tilt > max_tilt {
                max_tilt = tilt;
                tilt_id = *m;
            }
            let c = t_site[*m].translation.vector;
            let d = (c - centroid).dot(&n);
            let var = (n.transpose() * covs[*m].fixed_view::<3, 3>(0, 0) * n)[(0, 0)];
            if var > 0.0 && var.is_finite() {
                let r = d.abs() / var.sqrt();
                max_sigmas = max_sigmas.max(r);
                ratios.push(r * r);
            }
        }
        // A plane through the markers takes three of their out-of-plane freedoms.
        if members.len() >= 4 && ratios.len() + 3 > members.len() {
            chi2 += ratios.iter().sum::<f64>();
            dof += members.len() - 3;
        }
        reports.push(PlaneReport {
            name: name.to_string(),
            ids: members.iter().map(|m| markers[*m].0).collect(),
            rms_m: (sum2 / corners.len() as f64).sqrt(),
            max_m: max,
            worst_id: markers[worst].0,
            max_tilt_deg: max_tilt,
            tilt_id: markers[tilt_id].0,
            max_sigmas,
        });
    }
    let factor = if dof > 0 { chi2 / dof as f64 } else { 1.0 };
    (reports, factor)
}
