//! OpenCV dictionaries and the printed marker bitmap.

use crate::error::CvContext;
use crate::{MarkerFamily, VisionError};
use markhold_config::ConfigError;
use opencv::{aruco, core, prelude::*};

/// The marker as printed: `cells` x `cells` modules including the black border,
/// row-major, top row first, `true` = white.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MarkerBitmap {
    pub cells: usize,
    pub white: Vec<bool>,
}

impl MarkerBitmap {
    /// Module at (`row`, `col`), top-left first; out of range is white (the paper
    /// around the marker).
    pub fn is_white(&self, row: usize, col: usize) -> bool {
        if row >= self.cells || col >= self.cells {
            return true;
        }
        self.white[row * self.cells + col]
    }
}

pub(crate) fn dictionary(
    family: MarkerFamily,
) -> Result<core::Ptr<aruco::Dictionary>, VisionError> {
    aruco::get_predefined_dictionary(family.opencv_dictionary()).cv("get_predefined_dictionary")
}

/// The printed marker of `id` in `family`, exactly as OpenCV's detector expects it
/// (one black border module around the data bits).
pub fn marker_bitmap(family: MarkerFamily, id: u32) -> Result<MarkerBitmap, VisionError> {
    let dict = dictionary(family)?;
    let count = dict.bytes_list().rows();
    if id >= count as u32 {
        let expected = format!("an id of {family} in 0..{count}");
        return Err(ConfigError::new("marker.id", id, expected).into());
    }
    let cells = family.data_bits() + 2;
    // One pixel per module: draw_marker renders each module as a side_pixels/cells block.
    let mut img = core::Mat::default();
    aruco::draw_marker(&dict, id as i32, cells as i32, &mut img, 1).cv("draw_marker")?;
    let data = img.data_bytes().cv("draw_marker data")?;
    if img.rows() as usize != cells || img.cols() as usize != cells || data.len() < cells * cells {
        return Err(VisionError::OpenCv {
            op: "draw_marker",
            source: opencv::Error::new(
                core::StsBadSize,
                format!(
                    "expected a {cells}x{cells} image, got {}x{}",
                    img.cols(),
                    img.rows()
                ),
            ),
        });
    }
    let white = data[..cells * cells].iter().map(|&p| p > 127).collect();
    Ok(MarkerBitmap { cells, white })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn id_counts_match_opencv() {
        for f in MarkerFamily::all() {
            let d = dictionary(f).unwrap();
            assert_eq!(d.bytes_list().rows() as u32, f.id_count(), "{f}");
            assert_eq!(d.marker_size() as usize, f.data_bits(), "{f}");
        }
    }

    #[test]
    fn bitmap_has_black_border_and_differs_between_ids() {
        let a = marker_bitmap(MarkerFamily::AprilTag36h11, 0).unwrap();
        let b = marker_bitmap(MarkerFamily::AprilTag36h11, 1).unwrap();
        assert_eq!(a.cells, 8);
        for i in 0..a.cells {
            for (r, c) in [(0, i), (a.cells - 1, i), (i, 0), (i, a.cells - 1)] {
                assert!(!a.is_white(r, c), "border module ({r},{c}) is white");
            }
        }
        assert_ne!(a.white, b.white);
        let inner = a.white.iter().filter(|w| **w).count();
        assert!(inner > 5 && inner < 36, "{inner} white modules");
        assert!(marker_bitmap(MarkerFamily::Aruco4x4_50, 50).is_err());
        assert_eq!(
            marker_bitmap(MarkerFamily::Aruco7x7_1000, 999)
                .unwrap()
                .cells,
            9
        );
    }
}
