//! Averaging every pixel's colour ratios over the pixels of its own chroma around it.
//!
//! The ratios `hue::colour_ratios` gives a pixel come from its two to
//! four nearest sites of each missing channel: each such site's noise (a few percent in the
//! dark channels, albedo about 0.05) goes straight into the pixel's ratio. Within one material
//! the chroma (the colour with its brightness divided out) is the same at every pixel, while
//! the noise of neighbouring pixels' ratios is largely independent; averaging the chroma over
//! the pixels around that share it takes most of that noise out. Which pixels share it is read
//! off the ratios themselves: a joint bilateral filter in log chroma, whose range is set by the
//! chroma's own noise, measured on the image (a material's chroma differs from its
//! neighbour's by far more, tens of percent in some channel).

use rayon::prelude::*;

use super::mosaic::mirror;
use crate::plane::RgbPlanes;

/// Half width of the window the chroma is averaged over (5 x 5 pixels).
const RADIUS: isize = 2;

/// The 99th percentile of chi-squared with two degrees of freedom (`-2 ln 0.01`). A pixel's
/// log chroma has two degrees of freedom (three log channels less their mean); two pixels of
/// one material differ by noise alone, so their squared chroma distance over its variance per
/// degree of freedom is chi-squared with two: the range kernel keeps at least `e^-1/2` of the
/// weight for 99 % of such pairs.
const CHI2_2_99: f32 = 9.21;

/// Beyond this exponent a weight (below `e^-30`) is left out.
const CUTOFF: f32 = 30.0;

/// Replaces every pixel's colour `ratios` (each channel over the pixel's own, `pattern` giving
/// the own channel; 1 for it, all 0 for a black pixel) by the ratios of its log chroma averaged
/// over the window around it, each neighbour weighted by how close its chroma is to the
/// pixel's. Black pixels keep their ratios and weigh nothing.
pub fn smooth_chroma(pattern: [[u8; 2]; 2], ratios: &mut RgbPlanes) {
    let (w, h) = (ratios.width(), ratios.height());
    // Log chroma per pixel: log ratios less their mean (the own channel's log ratio is 0, so
    // this is the colour's log with the brightness removed). NaN marks a black pixel.
    let chroma: Vec<[f32; 3]> = {
        let [r, g, b] = ratios.channels();
        (0..w * h)
            .into_par_iter()
            .map(|i| {
                let logs = [r.data[i], g.data[i], b.data[i]].map(f32::ln);
                if logs.iter().all(|l| l.is_finite()) {
                    let mean = (logs[0] + logs[1] + logs[2]) / 3.0;
                    logs.map(|l| l - mean)
                } else {
                    [f32::NAN; 3]
                }
            })
            .collect()
    };
    let variance = chroma_noise(w, h, &chroma);
    // Weight exp(-d^2 / (2 s^2)) with s^2 = CHI2_2_99 * variance, the 99th percentile of a
    // same-material pair's d^2; a noise-free image (variance 0) averages only identical chroma.
    let inv = 1.0 / (2.0 * CHI2_2_99 * variance).max(f32::MIN_POSITIVE);
    let at = |x: isize, y: isize| chroma[mirror(y, h) * w + mirror(x, w)];
    ratios.par_rows_mut(|y, rows| {
        for x in 0..w {
            let centre = chroma[y * w + x];
            if centre[0].is_nan() {
                continue;
            }
            let (mut sum, mut weights) = ([0.0f32; 3], 0.0f32);
            for dy in -RADIUS..=RADIUS {
                for dx in -RADIUS..=RADIUS {
                    let q = at(x as isize + dx, y as isize + dy);
                    let d2 = (q[0] - centre[0]).powi(2)
                        + (q[1] - centre[1]).powi(2)
                        + (q[2] - centre[2]).powi(2);
                    // A black neighbour's NaN fails this test too.
                    let e = d2 * inv;
                    if e < CUTOFF {
                        let weight = (-e).exp();
                        for c in 0..3 {
                            sum[c] += weight * q[c];
                        }
                        weights += weight;
                    }
                }
            }
            let own = pattern[y % 2][x % 2] as usize;
            let mean = sum.map(|s| s / weights);
            for c in 0..3 {
                rows[c][x] = if c == own {
                    1.0
                } else {
                    (mean[c] - mean[own]).exp()
                };
            }
        }
    });
}

/// The variance per degree of freedom of the difference of two pixels' log chroma where they
/// are of one material, from the squared chroma distances of horizontally adjacent pixels: their median over `2 ln 2` (the median of chi-squared with
/// two degrees of freedom), robust to the pairs that straddle a colour edge as long as those
/// are under half. Every fourth row is enough.
fn chroma_noise(w: usize, h: usize, chroma: &[[f32; 3]]) -> f32 {
    let mut d2: Vec<f32> = (0..h)
        .into_par_iter()
        .step_by(4)
        .flat_map_iter(|y| {
            let row = &chroma[y * w..(y + 1) * w];
            row.windows(2).filter_map(|pair| {
                let [a, b] = [pair[0], pair[1]];
                let d = (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2);
                d.is_finite().then_some(d)
            })
        })
        .collect();
    if d2.is_empty() {
        return 0.0;
    }
    let mid = d2.len() / 2;
    let (_, median, _) = d2.select_nth_unstable_by(mid, f32::total_cmp);
    *median / (2.0 * std::f32::consts::LN_2)
}
