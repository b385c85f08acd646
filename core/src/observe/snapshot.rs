//! `--snapshot DIR`: every n-th frame as PNG, so a person can look at what the camera
//! saw. The folder is a recorded-frames camera (`frame_NNNNNN.png` and `frames.csv` with
//! each frame's stamp and exposure), so `run --camera frames:DIR` plays it back.

use std::path::{Path, PathBuf};

use markhold_camera::FrameRecorder;

use crate::error::SnapshotWrite;
use crate::pipeline::{FrameView, Observer};
use crate::CoreError;

/// Saves frames whose sequence number is a multiple of `every` into a folder.
pub struct Snapshots {
    dir: PathBuf,
    out: FrameRecorder,
    every: u64,
    /// The first failure; later frames are not tried.
    error: Option<SnapshotWrite>,
}

impl Snapshots {
    /// Creates `dir` if needed, with a fresh `frames.csv`.
    pub fn create(dir: &Path, every: u64) -> Result<Self, CoreError> {
        let out = FrameRecorder::create(dir).map_err(|source| CoreError::SnapshotCreate {
            dir: dir.to_path_buf(),
            source,
        })?;
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
            self.error = Some(SnapshotWrite {
                dir: self.dir.clone(),
                source: e,
            });
        }
    }
    fn finish(self: Box<Self>) -> Result<(), CoreError> {
        match self.error {
            Some(source) => Err(CoreError::SnapshotSave { source }),
            None => Ok(()),
        }
    }
}
