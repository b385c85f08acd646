//! Saving frames as PNG so a person can look at what the camera saw.

use std::path::Path;

use anyhow::Context;
use markhold_exposure::Frame;
use opencv::core::{Mat, Vector};

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
