//! OpenCV helpers the OpenCV backends share: the operation named in an error, and a
//! decoded image copied into a frame.

use crate::{CameraError, Frame};
use opencv::{core, imgproc, prelude::*};

/// Attach the name of the OpenCV operation to its error.
pub(crate) trait CvContext<T> {
    fn cv(self, op: &'static str) -> Result<T, CameraError>;
}

impl<T> CvContext<T> for Result<T, opencv::Error> {
    fn cv(self, op: &'static str) -> Result<T, CameraError> {
        self.map_err(|source| CameraError::OpenCv { op, source })
    }
}

/// Copy an 8-bit grey or BGR image into `frame` (grey).
pub(crate) fn mat_to_frame(
    img: &core::Mat,
    grey: &mut core::Mat,
    frame: &mut Frame,
) -> Result<(), opencv::Error> {
    let src = match img.channels() {
        1 => img,
        3 => {
            imgproc::cvt_color(img, grey, imgproc::COLOR_BGR2GRAY, 0)?;
            &*grey
        }
        4 => {
            imgproc::cvt_color(img, grey, imgproc::COLOR_BGRA2GRAY, 0)?;
            &*grey
        }
        n => {
            return Err(opencv::Error::new(
                core::StsBadArg,
                format!("{n} channels: expected grey or BGR"),
            ))
        }
    };
    if src.depth() != core::CV_8U {
        return Err(opencv::Error::new(
            core::StsBadArg,
            "pixel depth: expected 8 bits",
        ));
    }
    let (w, h) = (src.cols() as u32, src.rows() as u32);
    frame.resize(w, h);
    if src.is_continuous() {
        frame
            .data
            .copy_from_slice(&src.data_bytes()?[..(w * h) as usize]);
    } else {
        for y in 0..h as i32 {
            let row = src.row(y)?;
            let bytes = row.data_bytes()?;
            let start = y as usize * w as usize;
            frame.data[start..start + w as usize].copy_from_slice(&bytes[..w as usize]);
        }
    }
    Ok(())
}
