//! Two-dimensional FFTs over row-major complex buffers (rustfft rows, a blocked transpose,
//! rustfft rows again), shared by height integration and the weave-period search.

use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftDirection, FftPlanner};
use std::sync::Arc;

/// A 2-D transform of `width x height` that leaves its result transposed: after `forward`
/// the buffer holds `height`-long columns one after another (index `u * height + v` for
/// column frequency `u`, row frequency `v`); `inverse` takes that layout back to rows.
pub struct Fft2 {
    /// Width of the spatial data, in samples (the row transform's length).
    pub width: usize,
    /// Height of the spatial data, in samples (the column transform's length).
    pub height: usize,
    along_rows: [Arc<dyn Fft<f32>>; 2],
    along_cols: [Arc<dyn Fft<f32>>; 2],
}

impl Fft2 {
    /// Plans the forward and inverse transforms for `width x height` data.
    pub fn new(width: usize, height: usize) -> Self {
        let mut planner = FftPlanner::new();
        let mut plan = |n| {
            [
                planner.plan_fft(n, FftDirection::Forward),
                planner.plan_fft(n, FftDirection::Inverse),
            ]
        };
        let along_rows = plan(width);
        let along_cols = plan(height);
        Fft2 {
            width,
            height,
            along_rows,
            along_cols,
        }
    }

    /// Rows-major spatial data to the transposed spectrum (unnormalised).
    pub fn forward(&self, data: Vec<Complex32>) -> Vec<Complex32> {
        let mut data = data;
        rows(&self.along_rows[0], &mut data, self.width);
        let mut t = transpose(&data, self.width, self.height);
        rows(&self.along_cols[0], &mut t, self.height);
        t
    }

    /// The transposed spectrum back to row-major spatial data, divided by the pixel count so
    /// that `inverse(forward(x)) == x`.
    pub fn inverse(&self, spectrum: Vec<Complex32>) -> Vec<Complex32> {
        let mut t = spectrum;
        rows(&self.along_cols[1], &mut t, self.height);
        let mut data = transpose(&t, self.height, self.width);
        rows(&self.along_rows[1], &mut data, self.width);
        let scale = 1.0 / (self.width * self.height) as f32;
        data.par_iter_mut().for_each(|v| *v *= scale);
        data
    }
}

/// Angular frequency (radians per sample) of bin `k` of an `n`-point transform.
pub fn angular_frequency(k: usize, n: usize) -> f32 {
    let signed = if k <= n / 2 {
        k as f64
    } else {
        k as f64 - n as f64
    };
    (std::f64::consts::TAU * signed / n as f64) as f32
}

fn rows(fft: &Arc<dyn Fft<f32>>, data: &mut [Complex32], len: usize) {
    let scratch_len = fft.get_inplace_scratch_len();
    data.par_chunks_mut(len * 16).for_each_init(
        || vec![Complex32::default(); scratch_len],
        |scratch, chunk| fft.process_with_scratch(chunk, scratch),
    );
}

/// `width x height` row-major to `height x width` row-major, in cache-sized blocks.
pub fn transpose<T: Copy + Default + Send + Sync>(
    src: &[T],
    width: usize,
    height: usize,
) -> Vec<T> {
    const BLOCK: usize = 32;
    let mut dst = vec![T::default(); src.len()];
    dst.par_chunks_mut(height * BLOCK)
        .enumerate()
        .for_each(|(bx, out)| {
            let x0 = bx * BLOCK;
            let x1 = (x0 + BLOCK).min(width);
            for y0 in (0..height).step_by(BLOCK) {
                let y1 = (y0 + BLOCK).min(height);
                for x in x0..x1 {
                    let row = &mut out[(x - x0) * height..(x - x0 + 1) * height];
                    for y in y0..y1 {
                        row[y] = src[y * width + x];
                    }
                }
            }
        });
    dst
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_a_single_frequency_lands_in_its_bin() {
        let (w, h) = (12, 10);
        let data: Vec<Complex32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                Complex32::new(
                    (std::f32::consts::TAU * (3.0 * x / w as f32 + 2.0 * y / h as f32)).cos(),
                    0.0,
                )
            })
            .collect();
        let fft = Fft2::new(w, h);
        let spectrum = fft.forward(data.clone());
        // Energy sits at (u, v) = (3, 2) and its mirror (w-3, h-2), in the transposed layout.
        let at = |u: usize, v: usize| spectrum[u * h + v].norm();
        assert!((at(3, 2) - (w * h) as f32 / 2.0).abs() < 1e-3);
        assert!((at(w - 3, h - 2) - (w * h) as f32 / 2.0).abs() < 1e-3);
        assert!(at(3, 3) < 1e-3);
        let back = fft.inverse(spectrum);
        for (a, b) in back.iter().zip(&data) {
            assert!((a - b).norm() < 1e-4);
        }
    }
}
