//! Box downsampling into caller-owned buffers (a pyramid level without the levels).

use crate::ImageView;

/// Reusable buffers for [`Downsampler::run`].
#[derive(Debug, Clone, Default)]
pub struct Downsampler {
    acc: Vec<u32>,
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
        let f = factor.max(1);
        let (w, h) = (view.width / f, view.height / f);
        self.width = w;
        self.height = h;
        if self.acc.len() < w {
            self.acc.resize(w, 0);
        }
        if self.out.len() < w * h {
            self.out.resize(w * h, 0);
        }
        let area = (f * f) as u32;
        let half = area / 2;
        for oy in 0..h {
            let acc = &mut self.acc[..w];
            acc.fill(0);
            for y in oy * f..oy * f + f {
                let row = &view.row(y)[..w * f];
                for (a, block) in acc.iter_mut().zip(row.chunks_exact(f)) {
                    *a += block.iter().map(|&p| p as u32).sum::<u32>();
                }
            }
            for (o, a) in self.out[oy * w..oy * w + w].iter_mut().zip(acc.iter()) {
                *o = ((a + half) / area) as u8;
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
