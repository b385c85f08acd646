//! `--trace FILE.csv`: one row per frame, for a spreadsheet or a quick plot on the dock.

use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::pipeline::{FrameRecord, FrameView, Observer};
use crate::CoreError;

pub struct TraceWriter {
    path: PathBuf,
    out: BufWriter<std::fs::File>,
    /// The first write error; rows after it are dropped and the error reported at the end.
    error: Option<std::io::Error>,
}

impl TraceWriter {
    pub fn create(path: &Path) -> Result<Self, CoreError> {
        let file = std::fs::File::create(path).map_err(|source| CoreError::File {
            action: "creating --trace",
            path: path.to_path_buf(),
            source,
        })?;
        let mut w = Self {
            path: path.to_path_buf(),
            out: BufWriter::new(file),
            error: None,
        };
        w.write(format_args!(
            "seq,stamp_s,exposure_used_us,exposure_cmd_us,metric,used_frame,detected,\
             cam_marker_x_m,cam_marker_y_m,cam_marker_z_m,reproj_rms_px,\
             surge,sway,heave,roll,pitch,yaw,directive,latency_ms,markers\n"
        ));
        Ok(w)
    }

    fn write(&mut self, args: std::fmt::Arguments) {
        if self.error.is_none() {
            if let Err(e) = self.out.write_fmt(args) {
                self.error = Some(e);
            }
        }
    }

    /// One frame; `markers`: how many markers of the map its pose used.
    pub fn row(&mut self, r: &FrameRecord, markers: usize) {
        let t = r.t_cam_marker.map(|t| t.translation.vector);
        let (x, y, z) = t.map_or((f64::NAN, f64::NAN, f64::NAN), |v| (v.x, v.y, v.z));
        let e = r.effort;
        self.write(format_args!(
            "{},{:.4},{:.2},{:.2},{:.6e},{},{},{:.5},{:.5},{:.5},{:.3},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:?},{:.3},{}\n",
            r.seq,
            r.stamp_s,
            r.exposure_used_us,
            r.exposure.exposure_us,
            r.exposure.metric,
            r.exposure.used_frame as u8,
            r.detected as u8,
            x,
            y,
            z,
            r.reproj_rms_px,
            e.surge,
            e.sway,
            e.heave,
            e.roll,
            e.pitch,
            e.yaw,
            r.directive,
            r.latency_s * 1e3,
            markers,
        ));
    }

    /// Flush and report the first write error, naming the file.
    fn flush_and_report(&mut self) -> Result<(), CoreError> {
        let flushed = match self.error.take() {
            Some(e) => Err(e),
            None => self.out.flush(),
        };
        flushed.map_err(|source| CoreError::File {
            action: "writing --trace",
            path: self.path.clone(),
            source,
        })
    }
}

impl Observer for TraceWriter {
    fn name(&self) -> &'static str {
        "trace"
    }
    fn frame(&mut self, view: &FrameView<'_>) {
        self.row(view.rec, view.markers_in_view.len());
    }
    fn finish(mut self: Box<Self>) -> Result<(), CoreError> {
        self.flush_and_report()
    }
}
