//! Box downsampling into caller-owned buffers (a pyramid level without the levels).

use crate::ImageView;

/// Reusable buffers for [`Downsampler::run`].
#[derive(Debug, Clone, Default)]
pub struct Downsampler {
    /// Column sums of the `factor` rows of one block row (at most 32 * 255).
    acc: Vec<u16>,
    out: Vec<u8>,
    width: usize,
    height: usize,
}

impl Downsampler {
    pub fn new() -> Self {
        Self::default()
    }

    /// Average `factor` x `factor` blocks of `view` (a partial block at the right or
    /// bottom edge is dropped, as a pyramid level would). Returns the reduced image.
    pub fn run(&mut self, view: ImageView<'_>, factor: usize) -> ImageView<'_> {
        // u16 column sums hold up to 257 rows of 255.
        let f = factor.clamp(1, 257);
        let (w, h) = (view.width / f, view.height / f);
        self.width = w;
        self.height = h;
        let wf = w * f;
        if self.acc.len() < wf {
            self.acc.resize(wf, 0);
        }
        if self.out.len() < w * h {
            self.out.resize(w * h, 0);
        }
        let area = (f * f) as u32;
        let half = area / 2;
        for oy in 0..h {
            // Vertical sums first (u8 -> u16 lanes, vectorizes), then each block.
            let acc = &mut self.acc[..wf];
            acc.fill(0);
            for y in oy * f..oy * f + f {
                for (a, &p) in acc.iter_mut().zip(&view.row(y)[..wf]) {
                    *a += p as u16;
                }
            }
            for (o, block) in self.out[oy * w..oy * w + w]
                .iter_mut()
                .zip(acc.chunks_exact(f))
            {
                let sum: u32 = block.iter().map(|&a| a as u32).sum();
                *o = ((sum + half) / area) as u8;
            }
        }
        ImageView {
            width: w,
            height: h,
            stride: w,
            data: &self.out[..w * h],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn averages_blocks() {
        let data: Vec<u8> = (0..8 * 4).map(|i| (i % 8) as u8 * 10).collect();
        let view = ImageView::new(8, 4, &data).unwrap();
        let mut d = Downsampler::new();
        let out = d.run(view, 2);
        assert_eq!((out.width, out.height), (4, 2));
        // Columns 0,1 -> (0+10)/2 = 5; 2,3 -> 25; ...
        assert_eq!(out.row(0), &[5, 25, 45, 65]);
        assert_eq!(out.row(1), &[5, 25, 45, 65]);
        // A view smaller than one block gives an empty image, not a panic.
        let small = ImageView::new(3, 3, &data[..9]).unwrap();
        let out = d.run(small, 8);
        assert_eq!((out.width, out.height), (0, 0));
    }
}
