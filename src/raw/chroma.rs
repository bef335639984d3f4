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

use std::collections::HashMap;

use rayon::prelude::*;

use super::five_rows::FiveRows;
use super::mosaic::mirror;
use crate::math::exp_neg;
use crate::plane::RgbPlanes;

/// Half width of the window the chroma is averaged over (5 x 5 pixels).
const RADIUS: usize = 2;

/// The 99th percentile of chi-squared with two degrees of freedom (`-2 ln 0.01`). A pixel's
/// log chroma has two degrees of freedom (three log channels less their mean); two pixels of
/// one material differ by noise alone, so their squared chroma distance over its variance per
/// degree of freedom is chi-squared with two: the range kernel keeps at least `e^-1/2` of the
/// weight for 99 % of such pairs.
const CHI2_2_99: f32 = 9.21;

/// Beyond this exponent a weight (below `e^-30`) is left out.
const CUTOFF: f32 = 30.0;

/// Log chroma of one row, one vector per channel (structure of arrays, so that the window's
/// loop runs over contiguous values and vectorises). NaN marks a black pixel.
type ChromaRow = [Vec<f32>; 3];

/// Rows per band of [`smooth_chroma`]'s parallel work. A band overwrites its rows' ratios as
/// it goes, so the chroma of the two rows either side of each band boundary is taken first.
const BAND_ROWS: usize = 64;

/// Replaces every pixel's colour `ratios` (each channel over the pixel's own, `pattern` giving
/// the own channel; 1 for it, all 0 for a black pixel) by the ratios of its log chroma averaged
/// over the window around it, each neighbour weighted by how close its chroma is to the
/// pixel's. Black pixels keep their ratios and weigh nothing.
///
/// The chroma is computed a row at a time as the window reaches it, and only the window's
/// five rows are kept: chroma planes of the whole image were 192 MB of fresh memory at
/// 16 MP, for values each read within two rows of their own.
pub fn smooth_chroma(pattern: [[u8; 2]; 2], ratios: &mut RgbPlanes) {
    let (w, h) = (ratios.width(), ratios.height());
    let variance = chroma_noise(ratios);
    // Weight exp(-d^2 / (2 s^2)) with s^2 = CHI2_2_99 * variance, the 99th percentile of a
    // same-material pair's d^2; a noise-free image (variance 0) averages only identical chroma.
    let inv = 1.0 / (2.0 * CHI2_2_99 * variance).max(f32::MIN_POSITIVE);
    let halo = band_halo(ratios);
    ratios.par_bands_mut(BAND_ROWS, |y0, [r, g, b]| {
        let band = y0..y0 + r.len() / w.max(1);
        let mut kept = FiveRows::<ChromaRow>::starting_at(y0.saturating_sub(2));
        for y in band.clone() {
            // A row of this band is read two rows before the band overwrites it.
            kept.compute_to((y + 3).min(h), |k, chroma| {
                *chroma = if band.contains(&k) {
                    let row = (k - y0) * w..(k - y0 + 1) * w;
                    chroma_row([&r[row.clone()], &g[row.clone()], &b[row]])
                } else {
                    halo[&k].clone()
                };
            });
            let window = std::array::from_fn(|k| {
                let source = kept.row(mirror(y as isize + k as isize - 2, h));
                source.each_ref().map(Vec::as_slice)
            });
            let sums = window_sums(window, inv);
            let centre = kept.row(y);
            let row = (y - y0) * w..(y - y0 + 1) * w;
            let mut rows = [&mut r[row.clone()], &mut g[row.clone()], &mut b[row]];
            for x in 0..w {
                if centre[0][x].is_nan() {
                    continue;
                }
                let own = pattern[y % 2][x % 2] as usize;
                let mean: [f32; 3] = std::array::from_fn(|c| sums[c][x] / sums[3][x]);
                for (c, row) in rows.iter_mut().enumerate() {
                    row[x] = if c == own {
                        1.0
                    } else {
                        (mean[c] - mean[own]).exp()
                    };
                }
            }
        }
    });
}

/// The chroma of the rows a band of [`smooth_chroma`] reads but does not own, by row: the two
/// either side of every boundary between bands, taken before any band overwrites them.
fn band_halo(ratios: &RgbPlanes) -> HashMap<usize, ChromaRow> {
    let h = ratios.height();
    let planes = ratios.channels();
    (BAND_ROWS..h)
        .step_by(BAND_ROWS)
        .flat_map(|boundary| boundary - 2..(boundary + 2).min(h))
        .collect::<Vec<usize>>()
        .into_par_iter()
        .map(|k| (k, chroma_row(planes.map(|p| p.row(k)))))
        .collect()
}

/// One row's log chroma from its ratios (see [`log_chroma`]).
fn chroma_row([r, g, b]: [&[f32]; 3]) -> ChromaRow {
    let mut out: ChromaRow = std::array::from_fn(|_| Vec::with_capacity(r.len()));
    for ((&r, &g), &b) in r.iter().zip(g).zip(b) {
        let chroma = log_chroma([r, g, b]);
        for (o, v) in out.iter_mut().zip(chroma) {
            o.push(v);
        }
    }
    out
}

/// A pixel's log ratios less their mean (the own channel's log ratio is 0, so this is the
/// colour's log with the brightness removed); NaN where the pixel is black.
#[inline]
fn log_chroma(ratios: [f32; 3]) -> [f32; 3] {
    let logs = ratios.map(f32::ln);
    if logs.iter().all(|l| l.is_finite()) {
        let mean = (logs[0] + logs[1] + logs[2]) / 3.0;
        logs.map(|l| l - mean)
    } else {
        [f32::NAN; 3]
    }
}

/// Interior pixels per strip of [`window_sums`]: a strip's sums, centre and neighbour values
/// (10 rows of 256 floats) stay in the L1 cache across the window's 25 offsets, where a whole
/// 16 MP row's (140 KB) did not.
const STRIP: usize = 256;

/// Per pixel of a row, the weighted sums of its window's log chroma (three vectors) and of
/// the weights (the fourth); `rows[2 + dy]` is row `y + dy`'s chroma (mirrored at the top and
/// bottom borders by the caller), the window mirrored at the left and right borders here.
fn window_sums(rows: [[&[f32]; 3]; 5], inv: f32) -> [Vec<f32>; 4] {
    let w = rows[2][0].len();
    let mut sums: [Vec<f32>; 4] = std::array::from_fn(|_| vec![0.0f32; w]);
    let centre = rows[2];
    let radius = RADIUS as isize;
    let source_row = |dy: isize| rows[(dy + radius) as usize];
    // Adds the neighbours from `source[first..]` to the pixels `pixels`.
    let mut add = |pixels: std::ops::Range<usize>, source: [&[f32]; 3], first: usize| {
        let q = first..first + pixels.len();
        let [s0, s1, s2, s3] = &mut sums;
        accumulate(
            centre.map(|c| &c[pixels.clone()]),
            source.map(|c| &c[q.clone()]),
            inv,
            [s0, s1, s2, s3].map(|s| &mut s[pixels.clone()]),
        );
    };
    // Away from the left and right borders a pixel's neighbours at one offset are a shifted
    // slice, taken strip by strip; the pixels whose window crosses a border (every pixel of a
    // narrow row) are taken one at a time, mirrored. Each pixel adds its offsets in the same
    // order either way (rows, then columns), so the sums do not depend on the strips.
    let interior = (w > 2 * RADIUS).then_some(RADIUS..w - RADIUS);
    let border: Vec<usize> = match &interior {
        Some(_) => (0..RADIUS).chain(w - RADIUS..w).collect(),
        None => (0..w).collect(),
    };
    if let Some(pixels) = &interior {
        for start in pixels.clone().step_by(STRIP) {
            let strip = start..(start + STRIP).min(pixels.end);
            for dy in -radius..=radius {
                let source = source_row(dy);
                for dx in -radius..=radius {
                    add(strip.clone(), source, (strip.start as isize + dx) as usize);
                }
            }
        }
    }
    for dy in -radius..=radius {
        let source = source_row(dy);
        for dx in -radius..=radius {
            for &x in &border {
                add(x..x + 1, source, mirror(x as isize + dx, w));
            }
        }
    }
    sums
}

/// Adds each neighbour's weighted chroma and weight into `sums` (see [`accumulate_portable`]),
/// on AVX-512 or AVX2 where the CPU has it (the same arithmetic, sixteen or eight pixels at a
/// time: no fused multiply-add, so the same bits; the standard library caches the CPU check).
fn accumulate(centre: [&[f32]; 3], neighbour: [&[f32]; 3], inv: f32, sums: [&mut [f32]; 4]) {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx512f") {
        // SAFETY: the CPU has AVX-512F (checked above).
        return unsafe { accumulate_avx512(centre, neighbour, inv, sums) };
    }
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked above).
        return unsafe { accumulate_avx2(centre, neighbour, inv, sums) };
    }
    accumulate_portable(centre, neighbour, inv, sums)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn accumulate_avx512(
    centre: [&[f32]; 3],
    neighbour: [&[f32]; 3],
    inv: f32,
    sums: [&mut [f32]; 4],
) {
    accumulate_portable(centre, neighbour, inv, sums)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn accumulate_avx2(
    centre: [&[f32]; 3],
    neighbour: [&[f32]; 3],
    inv: f32,
    sums: [&mut [f32]; 4],
) {
    accumulate_portable(centre, neighbour, inv, sums)
}

/// For every pixel i: the neighbour's weight `exp(-d^2 inv)`, `d` the distance of its chroma
/// from the centre's, added with its weighted chroma into `sums` (chroma, chroma, chroma,
/// weight); a weight past [`CUTOFF`], or a black (NaN) neighbour, adds nothing. Branch-free
/// (selects, no skips), so that it vectorises.
#[inline(always)]
fn accumulate_portable(
    [c0, c1, c2]: [&[f32]; 3],
    [q0, q1, q2]: [&[f32]; 3],
    inv: f32,
    [s0, s1, s2, s3]: [&mut [f32]; 4],
) {
    let n = c0.len();
    let (c1, c2, q0, q1, q2) = (&c1[..n], &c2[..n], &q0[..n], &q1[..n], &q2[..n]);
    let (s0, s1, s2, s3) = (&mut s0[..n], &mut s1[..n], &mut s2[..n], &mut s3[..n]);
    for i in 0..n {
        let (d0, d1, d2) = (q0[i] - c0[i], q1[i] - c1[i], q2[i] - c2[i]);
        let e = (d0 * d0 + d1 * d1 + d2 * d2) * inv;
        // NaN (a black neighbour) fails this test too.
        let keep = e < CUTOFF;
        // A multiply by 0 or 1 and zeroed neighbours, not `if keep { s += .. }`: the compiler
        // turns that into masked stores, several times slower than the arithmetic.
        let weight = exp_neg(if keep { e } else { 0.0 }) * f32::from(u8::from(keep));
        let q = [q0[i], q1[i], q2[i]].map(|v| if keep { v } else { 0.0 });
        s0[i] += weight * q[0];
        s1[i] += weight * q[1];
        s2[i] += weight * q[2];
        s3[i] += weight;
    }
}

/// The variance per degree of freedom of the difference of two pixels' log chroma where they
/// are of one material, from the squared chroma distances of horizontally adjacent pixels:
/// their median over `2 ln 2` (the median of chi-squared with two degrees of freedom), robust
/// to the pairs that straddle a colour edge as long as those are under half. Every fourth row
/// is enough.
fn chroma_noise(ratios: &RgbPlanes) -> f32 {
    let (w, h) = (ratios.width(), ratios.height());
    let planes = ratios.channels();
    let mut d2: Vec<f32> = (0..h)
        .into_par_iter()
        .step_by(4)
        .flat_map_iter(|y| {
            let [c0, c1, c2] = chroma_row(planes.map(|p| p.row(y)));
            (1..w).filter_map(move |x| {
                let d = (c0[x] - c0[x - 1]).powi(2)
                    + (c1[x] - c1[x - 1]).powi(2)
                    + (c2[x] - c2[x - 1]).powi(2);
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The filter as first written: per pixel, its window with mirrored borders and the
    /// standard library's exponential.
    fn reference(pattern: [[u8; 2]; 2], ratios: &RgbPlanes) -> RgbPlanes {
        let (w, h) = (ratios.width(), ratios.height());
        let [r, g, b] = ratios.channels();
        let inv = 1.0 / (2.0 * CHI2_2_99 * chroma_noise(ratios)).max(f32::MIN_POSITIVE);
        let at = |x: isize, y: isize| {
            let i = mirror(y, h) * w + mirror(x, w);
            log_chroma([r.data[i], g.data[i], b.data[i]])
        };
        let mut out = ratios.clone();
        out.par_rows_mut(|y, rows| {
            for x in 0..w {
                let centre = at(x as isize, y as isize);
                if centre[0].is_nan() {
                    continue;
                }
                let (mut sum, mut weights) = ([0.0f32; 3], 0.0f32);
                for dy in -2..=2isize {
                    for dx in -2..=2isize {
                        let q = at(x as isize + dx, y as isize + dy);
                        let e = ((q[0] - centre[0]).powi(2)
                            + (q[1] - centre[1]).powi(2)
                            + (q[2] - centre[2]).powi(2))
                            * inv;
                        if e < CUTOFF {
                            let weight = (-e).exp();
                            (0..3).for_each(|c| sum[c] += weight * q[c]);
                            weights += weight;
                        }
                    }
                }
                let own = pattern[y % 2][x % 2] as usize;
                for c in 0..3 {
                    if c != own {
                        rows[c][x] = ((sum[c] - sum[own]) / weights).exp();
                    }
                }
            }
        });
        out
    }

    /// Ratios of two materials in stripes, with noise and black pixels, own channel 1.
    fn ratios(w: usize, h: usize, pattern: [[u8; 2]; 2]) -> RgbPlanes {
        let mut out = RgbPlanes::new(w, h);
        out.par_rows_mut(|y, rows| {
            for x in 0..w {
                let own = pattern[y % 2][x % 2] as usize;
                let hash = ((x * 7919 + y * 104_729) % 1000) as f32 / 1000.0;
                let material = if (x / 3 + y / 5) % 2 == 0 {
                    [0.6, 1.0, 0.3]
                } else {
                    [1.4, 1.0, 2.5]
                };
                for c in 0..3 {
                    rows[c][x] = if (x * 31 + y * 17) % 23 == 0 {
                        0.0
                    } else if c == own {
                        1.0
                    } else {
                        material[c] / material[own] * (1.0 + 0.05 * (hash - 0.5))
                    };
                }
            }
        });
        out
    }

    #[test]
    fn the_vectorised_window_matches_the_per_pixel_filter() {
        let pattern = [[0, 1], [1, 2]];
        // 600 wide: interior rows in several strips (STRIP), the last one short. 150 and 130
        // high: three bands (BAND_ROWS), the last of 22 rows or of 2.
        for (w, h) in [
            (37, 29),
            (5, 6),
            (4, 3),
            (1, 7),
            (600, 9),
            (41, 150),
            (9, 130),
        ] {
            let input = ratios(w, h, pattern);
            let expected = reference(pattern, &input);
            let mut got = input.clone();
            smooth_chroma(pattern, &mut got);
            // The weights differ by exp_neg's relative error (under 2e-6), which moves a
            // weighted mean of log chroma by at most that times the chroma's spread in the
            // window (|log chroma| < 2 here, so a spread under 4), for each of the two means a
            // ratio compares; f32 sums of 25 terms add a few ulp.
            let allowed = 2.0 * 2e-6 * 4.0 + 1e-6;
            for c in 0..3 {
                for (i, (a, b)) in got.channels()[c]
                    .data
                    .iter()
                    .zip(&expected.channels()[c].data)
                    .enumerate()
                {
                    let off = if *b == 0.0 {
                        a.abs()
                    } else {
                        (a / b).ln().abs()
                    };
                    assert!(off <= allowed, "{w}x{h} channel {c} pixel {i}: {a} vs {b}");
                }
            }
        }
    }
}
