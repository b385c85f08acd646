//! `--snapshot DIR`: every n-th frame as PNG, so a person can look at what the camera
//! saw. The folder is a recorded-frames camera (`frame_NNNNNN.png` and `frames.csv` with
//! each frame's stamp and exposure), so `run --camera frames:DIR` plays it back.

use std::path::{Path, PathBuf};

use anyhow::Context;
use markhold_camera::FrameRecorder;

use crate::pipeline::{FrameView, Observer};

/// Saves frames whose sequence number is a multiple of `every` into a folder.
pub struct Snapshots {
    dir: PathBuf,
    out: FrameRecorder,
    every: u64,
    /// The first failure; later frames are not tried.
    error: Option<anyhow::Error>,
}

impl Snapshots {
    /// Creates `dir` if needed, with a fresh `frames.csv`.
    pub fn create(dir: &Path, every: u64) -> anyhow::Result<Self> {
        let out = FrameRecorder::create(dir)
            .with_context(|| format!("creating --snapshot {}", dir.display()))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            out,
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
        if let Err(e) = self.out.write(view.frame) {
            self.error = Some(anyhow::Error::new(e).context(format!("in {}", self.dir.display())));
        }
    }
    fn finish(self: Box<Self>) -> anyhow::Result<()> {
        match self.error {
            Some(e) => Err(e.context("saving snapshots")),
            None => Ok(()),
        }
    }
}
