//! One row's right-hand sides for the sites' fits: `sum_k v_k start_k` and `sum_k v_k step_k`
//! per site over every frame (`v_k` the site's white-balanced sample in frame k, `start_k` and
//! `step_k` its cell's shading vector and its change across the cell), and which sites are
//! saturated in some frame.
//!
//! A block of a cell's sites at a time, every frame into sums kept in registers: the six
//! sums of a whole row (240 KB of f64 at 16 MP) no longer go through memory once per frame.
//! Each sum is still taken frame by frame from zero, a product then an add (no fused
//! multiply-add), so the bits are those of summing a frame at a time over the whole row.

use super::{RowCell, ShadingField};
use crate::raw::mosaic::LinearMosaic;

/// Sites summed together: a shading cell's width in the rig's field (16 samples), two
/// AVX-512 vectors of f64 per sum.
const BLOCK: usize = 16;

#[derive(Default)]
pub(super) struct RowSums {
    /// Each frame's samples of the row, where it keeps them as DN.
    values: Vec<Vec<f32>>,
    start: [Vec<f64>; 3],
    step: [Vec<f64>; 3],
    /// Whether each site is saturated in some frame.
    pub(super) saturated: Vec<bool>,
}

impl RowSums {
    /// Row `y`'s sums and flags, over `frames` white-balanced by `inverse` (per frame and
    /// channel), with `cells` the row's cells of `field`.
    pub(super) fn accumulate(
        &mut self,
        frames: &[LinearMosaic],
        inverse: &[[f64; 3]],
        field: &ShadingField,
        cells: &[RowCell],
        y: usize,
    ) {
        let w = field.width;
        self.saturated.clear();
        self.saturated.resize(w, false);
        for flags in frames.iter().filter_map(|f| f.saturated_row(y)) {
            for (s, &f) in self.saturated.iter_mut().zip(flags) {
                *s |= f;
            }
        }
        // Every site is written: the cells cover the row (see `ShadingField::cell_columns`).
        for plane in self.start.iter_mut().chain(&mut self.step) {
            plane.resize(w, 0.0);
        }
        self.values.resize_with(frames.len(), Vec::new);
        let rows: Vec<&[f32]> = frames
            .iter()
            .zip(&mut self.values)
            .map(|(frame, scratch)| frame.row(y, scratch))
            .collect();
        // Each frame's white balance by column parity (the row's two CFA channels).
        let pattern = frames[0].pattern[y % 2].map(usize::from);
        let balance: Vec<[f64; 2]> = inverse.iter().map(|inv| pattern.map(|c| inv[c])).collect();
        let sums = Sums {
            rows: &rows,
            balance: &balance,
        };
        sums.sum_into(field, cells, &mut self.start, &mut self.step);
    }

    /// Site `x`'s two sums. Inlined: the fit's loop over a cell's sites vectorises with it.
    #[inline(always)]
    pub(super) fn rhs(&self, x: usize) -> ([f64; 3], [f64; 3]) {
        (
            std::array::from_fn(|m| self.start[m][x]),
            std::array::from_fn(|m| self.step[m][x]),
        )
    }
}

/// A row's samples in every frame and the frames' white balance by column parity.
struct Sums<'a> {
    rows: &'a [&'a [f32]],
    balance: &'a [[f64; 2]],
}

impl Sums<'_> {
    /// Every cell's sums into `start` and `step`, on AVX-512 or AVX2 where the CPU has it
    /// (the same arithmetic, more sites per instruction: the same bits).
    fn sum_into(
        &self,
        field: &ShadingField,
        cells: &[RowCell],
        start: &mut [Vec<f64>; 3],
        step: &mut [Vec<f64>; 3],
    ) {
        #[cfg(target_arch = "x86_64")]
        if is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has AVX-512F (checked above).
            return unsafe { self.sum_into_avx512(field, cells, start, step) };
        }
        #[cfg(target_arch = "x86_64")]
        if is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked above).
            return unsafe { self.sum_into_avx2(field, cells, start, step) };
        }
        self.sum_into_portable(field, cells, start, step)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn sum_into_avx512(
        &self,
        field: &ShadingField,
        cells: &[RowCell],
        start: &mut [Vec<f64>; 3],
        step: &mut [Vec<f64>; 3],
    ) {
        self.sum_into_portable(field, cells, start, step)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn sum_into_avx2(
        &self,
        field: &ShadingField,
        cells: &[RowCell],
        start: &mut [Vec<f64>; 3],
        step: &mut [Vec<f64>; 3],
    ) {
        self.sum_into_portable(field, cells, start, step)
    }

    #[inline(always)]
    fn sum_into_portable(
        &self,
        field: &ShadingField,
        cells: &[RowCell],
        start: &mut [Vec<f64>; 3],
        step: &mut [Vec<f64>; 3],
    ) {
        for (c, cell) in cells.iter().enumerate() {
            let columns = field.cell_columns(c, cells.len());
            let mut x = columns.start;
            while x + BLOCK <= columns.end {
                self.block::<BLOCK>(cell, x, start, step);
                x += BLOCK;
            }
            for x in x..columns.end {
                self.block::<1>(cell, x, start, step);
            }
        }
    }

    /// The sums of the `N` sites from column `x0` on, all of `cell`.
    #[inline(always)]
    fn block<const N: usize>(
        &self,
        cell: &RowCell,
        x0: usize,
        start: &mut [Vec<f64>; 3],
        step: &mut [Vec<f64>; 3],
    ) {
        let mut by_start = [[0.0f64; N]; 3];
        let mut by_step = [[0.0f64; N]; 3];
        for (k, (row, balance)) in self.rows.iter().zip(self.balance).enumerate() {
            let samples = &row[x0..x0 + N];
            let v: [f64; N] = std::array::from_fn(|j| samples[j] as f64 * balance[(x0 + j) % 2]);
            let (a, d) = (cell.start[k], cell.step[k]);
            for m in 0..3 {
                for j in 0..N {
                    by_start[m][j] += v[j] * a[m];
                    by_step[m][j] += v[j] * d[m];
                }
            }
        }
        for m in 0..3 {
            start[m][x0..x0 + N].copy_from_slice(&by_start[m]);
            step[m][x0..x0 + N].copy_from_slice(&by_step[m]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::random_stack;
    use super::*;

    /// The sums as they were taken before blocks: a frame at a time over the whole row.
    fn sums_a_frame_at_a_time(
        frames: &[LinearMosaic],
        inverse: &[[f64; 3]],
        field: &ShadingField,
        cells: &[RowCell],
        y: usize,
    ) -> [Vec<f64>; 6] {
        let w = field.width;
        let pattern = frames[0].pattern[y % 2].map(usize::from);
        let mut sums: [Vec<f64>; 6] = std::array::from_fn(|_| vec![0.0; w]);
        let mut scratch = Vec::new();
        for (k, frame) in frames.iter().enumerate() {
            let values = frame.row(y, &mut scratch);
            let balanced: Vec<f64> = (0..w)
                .map(|x| values[x] as f64 * inverse[k][pattern[x % 2]])
                .collect();
            for (c, cell) in cells.iter().enumerate() {
                for x in field.cell_columns(c, cells.len()) {
                    for m in 0..3 {
                        sums[m][x] += balanced[x] * cell.start[k][m];
                        sums[3 + m][x] += balanced[x] * cell.step[k][m];
                    }
                }
            }
        }
        sums
    }

    #[test]
    fn block_sums_equal_a_frame_at_a_time_bit_for_bit() {
        // Cells of 16 (whole blocks), of 8 (none) and of 24 (a block and a tail); widths
        // whose last cell is wider than the rest.
        for (step, w) in [(16, 53), (8, 37), (24, 61)] {
            let (frames, colours, field, _) = random_stack((w, 9), step, 3);
            let inverse: Vec<[f64; 3]> =
                colours.iter().map(|g| g.map(|v| 1.0 / v as f64)).collect();
            let mut sums = RowSums::default();
            for y in 0..9 {
                let nodes = field.row_nodes(y);
                let cells = field.row_cells(&nodes);
                sums.accumulate(&frames, &inverse, &field, &cells, y);
                let want = sums_a_frame_at_a_time(&frames, &inverse, &field, &cells, y);
                for x in 0..w {
                    let (start, step_sums) = sums.rhs(x);
                    for m in 0..3 {
                        assert_eq!(start[m].to_bits(), want[m][x].to_bits(), "{x},{y} {m}");
                        assert_eq!(step_sums[m].to_bits(), want[3 + m][x].to_bits());
                    }
                    let saturated = frames.iter().any(|f| f.saturated[y * w + x]);
                    assert_eq!(sums.saturated[x], saturated, "{x},{y}");
                }
            }
        }
    }
}
