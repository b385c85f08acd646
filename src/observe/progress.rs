//! The progress bar of a run on the terminal: frames done, loop time, exposure, marker.

use indicatif::{ProgressBar, ProgressStyle};

use crate::pipeline::{FrameView, Observer};

pub struct Progress {
    bar: ProgressBar,
}

impl Progress {
    /// A bar over `frames` frames (hidden when `quiet`).
    pub fn new(frames: u64, quiet: bool) -> Self {
        let bar = if quiet {
            ProgressBar::hidden()
        } else {
            let b = ProgressBar::new(frames);
            b.set_style(
                ProgressStyle::with_template(
                    "{spinner} {elapsed_precise} [{bar:30}] {pos}/{len} frames {msg}",
                )
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            b
        };
        Self { bar }
    }
}

impl Observer for Progress {
    fn name(&self) -> &'static str {
        "progress"
    }
    fn frame(&mut self, view: &FrameView<'_>) {
        let rec = view.rec;
        self.bar.inc(1);
        if rec.seq.is_multiple_of(15) {
            self.bar.set_message(format!(
                "t={:.1}s exp={:.0}us {}",
                rec.stamp_s,
                rec.exposure.exposure_us,
                if rec.detected { "marker" } else { "no marker" }
            ));
        }
    }
    fn finish(self: Box<Self>) -> anyhow::Result<()> {
        self.bar.finish_and_clear();
        Ok(())
    }
}
