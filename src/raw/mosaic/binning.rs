//! 2x2 binning of a mosaic's sample rows into half-resolution RGB: the loop `raw::pass`
//! feeds row by row, and the per-row kernels (one per Bayer layout, which the compiler
//! vectorises, and a general one).

use rayon::prelude::*;

use super::Resolution;
use crate::plane::{LightFrame, Mask, RgbPlanes};

/// One sample row as [`bin_rows`] bins it: linear values and saturation flags, `width` of
/// each, and `scratch` for whatever the row's source needs (a row linearised from DN).
#[derive(Default)]
pub(in crate::raw) struct SampleRow {
    pub values: Vec<f32>,
    pub saturated: Vec<bool>,
    pub scratch: Vec<f32>,
}

/// 2x2 binning of a `width x height` mosaic laid out as `pattern`, whose sample row `y`
/// `fill_row(y, row, acc)` writes into `row` (values and flags, `width` each): R and B of each
/// cell, the mean of its two G, saturated where any of its samples is. Rows of cells run in
/// parallel, each with its own `acc` from `new_acc`, returned one per row of cells. Whole rows
/// are filled, the odd last column's sample too (not binned), so `fill_row` can count what it
/// reads; an odd last row is not filled.
pub(in crate::raw) fn bin_rows<A: Send>(
    (width, height): (usize, usize),
    pattern: [[u8; 2]; 2],
    new_acc: impl Fn() -> A + Sync,
    fill_row: impl Fn(usize, &mut SampleRow, &mut A) + Sync,
) -> (LightFrame, Vec<A>) {
    let (w, h) = Resolution::Half.size(width, height);
    let mut rgb = RgbPlanes::new(w, h);
    let mut saturated = Mask::new(w, h, false);
    let accs = rgb
        .r
        .data
        .par_chunks_mut(w.max(1))
        .zip(rgb.g.data.par_chunks_mut(w.max(1)))
        .zip(rgb.b.data.par_chunks_mut(w.max(1)))
        .zip(saturated.data.par_chunks_mut(w.max(1)))
        .enumerate()
        .map_init(
            || [SampleRow::default(), SampleRow::default()],
            |[top, bottom], (v, (((r, g), b), sat))| {
                let mut acc = new_acc();
                fill_row(2 * v, top, &mut acc);
                fill_row(2 * v + 1, bottom, &mut acc);
                bin_row_pair(pattern, [top, bottom], [r, g, b], sat);
                acc
            },
        )
        .collect();
    let frame = LightFrame {
        rgb,
        saturated: Some(saturated),
        cfa: None,
        dn: None,
        cfa_dn: None,
    };
    (frame, accs)
}

/// Bins a row of cells from its two sample rows into `r`, `g`, `b` and `saturated`, each
/// cell's samples summed from 0.0, top row first, left to right.
fn bin_row_pair(
    pattern: [[u8; 2]; 2],
    rows: [&SampleRow; 2],
    out: [&mut [f32]; 3],
    saturated: &mut [bool],
) {
    // The four Bayer layouts get a loop each with the sites' places fixed (R and B at cell
    // places 0-3, top row first), which the compiler vectorises; any other layout, the
    // general loop. Both add in the same order, so they give the same bits.
    match pattern {
        [[0, 1], [1, 2]] => bin_bayer_row::<0, 3>(rows, out, saturated),
        [[2, 1], [1, 0]] => bin_bayer_row::<3, 0>(rows, out, saturated),
        [[1, 0], [2, 1]] => bin_bayer_row::<1, 2>(rows, out, saturated),
        [[1, 2], [0, 1]] => bin_bayer_row::<2, 1>(rows, out, saturated),
        _ => bin_any_row(pattern, rows, out, saturated),
    }
}

/// [`bin_row_pair`] for a Bayer cell with R at place `R` and B at place `B` (0, 1: top row,
/// left to right; 2, 3: bottom row) and G at the other two.
fn bin_bayer_row<const R: usize, const B: usize>(
    [top, bottom]: [&SampleRow; 2],
    [r, g, b]: [&mut [f32]; 3],
    saturated: &mut [bool],
) {
    let mut greens = (0..4).filter(|&p| p != R && p != B);
    let (g1, g2) = (greens.next().unwrap_or(0), greens.next().unwrap_or(0));
    let n = r.len();
    let cells = top.values[..2 * n]
        .chunks_exact(2)
        .zip(bottom.values[..2 * n].chunks_exact(2));
    let outs = r.iter_mut().zip(g.iter_mut()).zip(b.iter_mut());
    for (((r, g), b), (t, d)) in outs.zip(cells) {
        let at = |p: usize| if p < 2 { t[p] } else { d[p - 2] };
        *r = 0.0 + at(R);
        *g = 0.5 * ((0.0 + at(g1)) + at(g2));
        *b = 0.0 + at(B);
    }
    let flags = top.saturated[..2 * n]
        .chunks_exact(2)
        .zip(bottom.saturated[..2 * n].chunks_exact(2));
    for (sat, (t, d)) in saturated[..n].iter_mut().zip(flags) {
        *sat = (t[0] | t[1]) | (d[0] | d[1]);
    }
}

/// [`bin_row_pair`] for any layout.
fn bin_any_row(
    pattern: [[u8; 2]; 2],
    rows: [&SampleRow; 2],
    [r, g, b]: [&mut [f32]; 3],
    saturated: &mut [bool],
) {
    for (u, ((r, g), (b, sat))) in r
        .iter_mut()
        .zip(g.iter_mut())
        .zip(b.iter_mut().zip(saturated.iter_mut()))
        .enumerate()
    {
        let mut sum = [0.0f32; 3];
        let mut any_saturated = false;
        for (row, channels) in rows.iter().zip(pattern) {
            for (i, channel) in channels.into_iter().enumerate() {
                sum[channel as usize] += row.values[2 * u + i];
                any_saturated |= row.saturated[2 * u + i];
            }
        }
        *r = sum[0];
        *g = 0.5 * sum[1];
        *b = sum[2];
        *sat = any_saturated;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raw::mosaic::Mosaic;

    /// The Bayer layouts' fixed-place loops give the general loop's bits, saturation flags
    /// included, on values of both signs, signed zeros and non-finite ones.
    #[test]
    fn bayer_binning_loops_match_the_general_one() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(11);
        let n = 37;
        let specials = [0.0f32, -0.0, f32::NAN, f32::INFINITY, -1e-40, 65535.0];
        let mut row = || SampleRow {
            values: (0..2 * n + 1)
                .map(|_| match rng.gen_range(0..8) {
                    0 => specials[rng.gen_range(0..specials.len())],
                    _ => rng.gen_range(-50.0f32..4000.0),
                })
                .collect(),
            saturated: (0..2 * n + 1).map(|_| rng.gen_range(0..5) == 0).collect(),
            scratch: Vec::new(),
        };
        let rows = [row(), row()];
        for pattern in ["RGGB", "BGGR", "GRBG", "GBRG"] {
            let pattern = Mosaic::parse_pattern(pattern).unwrap();
            type Binner = fn([[u8; 2]; 2], [&SampleRow; 2], [&mut [f32]; 3], &mut [bool]);
            let run = |bin: Binner| {
                let (mut r, mut g, mut b, mut sat) =
                    (vec![7.0; n], vec![7.0; n], vec![7.0; n], vec![false; n]);
                bin(
                    pattern,
                    [&rows[0], &rows[1]],
                    [&mut r, &mut g, &mut b],
                    &mut sat,
                );
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                (bits(&r), bits(&g), bits(&b), sat)
            };
            let (fast, general) = (run(bin_row_pair), run(bin_any_row));
            assert_eq!(fast, general, "{pattern:?}");
        }
    }
}
