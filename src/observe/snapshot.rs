//! `--snapshot DIR`: every n-th frame as PNG, so a person can look at what the camera saw.

use std::path::{Path, PathBuf};

use anyhow::Context;
use markhold_exposure::Frame;
use opencv::core::{Mat, Vector};

use crate::pipeline::{FrameView, Observer};

/// Write `frame` as an 8-bit grey PNG.
pub fn save_png(frame: &Frame, path: &Path) -> anyhow::Result<()> {
    let mat = Mat::new_rows_cols_with_data(frame.height as i32, frame.width as i32, &frame.data)
        .context("wrapping the frame for PNG encoding")?;
    let name = path.display();
    let ok = opencv::imgcodecs::imwrite(path, &mat, &Vector::new())
        .with_context(|| format!("writing {name}"))?;
    anyhow::ensure!(ok, "writing {name}: the PNG encoder refused the file");
    Ok(())
}

/// Saves frames whose sequence number is a multiple of `every` into a folder.
pub struct Snapshots {
    dir: PathBuf,
    every: u64,
    /// The first failure; later frames are not tried.
    error: Option<anyhow::Error>,
}

impl Snapshots {
    /// Creates `dir` if needed.
    pub fn create(dir: &Path, every: u64) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("creating --snapshot {}", dir.display()))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            every: every.max(1),
            error: None,
        })
    }
}

impl Observer for Snapshots {
    fn name(&self) -> &'static str {
        "snapshots"
    }
    fn frame(&mut self, view: &FrameView<'_>) {
        if self.error.is_some() || !view.rec.seq.is_multiple_of(self.every) {
            return;
        }
        let path = self.dir.join(format!("frame-{:06}.png", view.rec.seq));
        if let Err(e) = save_png(view.frame, &path) {
            self.error = Some(e);
        }
    }
    fn finish(self: Box<Self>) -> anyhow::Result<()> {
        match self.error {
            Some(e) => Err(e.context("saving snapshots")),
            None => Ok(()),
        }
    }
}
