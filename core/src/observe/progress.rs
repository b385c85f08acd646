//! The progress bar of a run on the terminal: frames done, loop time, exposure, marker.
//!
//! The bar is a tracing span (`indicatif.pb_show`) that the binary's subscriber draws with
//! tracing-indicatif, so log lines are printed above it instead of through it. Without
//! that subscriber (a library user, a test) the span does nothing.

use crate::CoreError;
use tracing::Span;
use tracing_indicatif::span_ext::IndicatifSpanExt;

use crate::pipeline::{FrameView, Observer};

/// A progress-bar span of `len` steps with `template`, started (none when `quiet`).
/// The bar draws only on a terminal.
pub fn bar_span(len: u64, template: &str, quiet: bool) -> Span {
    if quiet {
        return Span::none();
    }
    let span = tracing::info_span!("progress", indicatif.pb_show = true);
    let style = indicatif::ProgressStyle::with_template(template)
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> ");
    span.pb_set_style(&style);
    span.pb_set_length(len);
    span.pb_start();
    span
}

pub struct Progress {
    bar: Span,
    /// The message, rewritten in place (no allocation per frame).
    msg: String,
}

impl Progress {
    /// A bar over `frames` frames (hidden when `quiet`).
    pub fn new(frames: u64, quiet: bool) -> Self {
        Self {
            bar: bar_span(
                frames,
                "{spinner} {elapsed_precise} [{bar:30}] {pos}/{len} frames {msg}",
                quiet,
            ),
            msg: String::with_capacity(64),
        }
    }
}

impl Observer for Progress {
    fn name(&self) -> &'static str {
        "progress"
    }
    fn frame(&mut self, view: &FrameView<'_>) {
        if self.bar.is_none() {
            return;
        }
        let rec = view.rec;
        self.bar.pb_inc(1);
        if rec.seq.is_multiple_of(15) {
            use std::fmt::Write;
            self.msg.clear();
            let _ = write!(
                self.msg,
                "t={:.1}s exp={:.0}us {}",
                rec.stamp_s,
                rec.exposure.exposure_us,
                if rec.detected { "marker" } else { "no marker" }
            );
            self.bar.pb_set_message(&self.msg);
        }
    }
    fn finish(self: Box<Self>) -> Result<(), CoreError> {
        // Closing the span clears the bar.
        Ok(())
    }
}
