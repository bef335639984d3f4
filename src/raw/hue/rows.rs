//! [`super::ratio_along`] for the interior pixels of a row, all pixels of one column parity at
//! once: the same arithmetic in the same order (so the same bits), laid out so that it
//! vectorises. Per pixel and missing channel the scalar version takes 2 to 4 data-dependent
//! branches per neighbour (which direction continues, whether the far flank is the same
//! material, whether a weight counts) and reads its sites through the mirrored border index;
//! at 16 MP that was about a second of the demosaic. Here every neighbour's candidate is
//! computed branch-free over a row of pixels, from the sites' fields split by column parity
//! into contiguous arrays.

use super::{continuity_change, neighbours_of_channel, CONTINUITY_SCALE, FLANK_CONTINUES};
use crate::math::exp_neg;
use crate::raw::shading::SiteFit;

/// One row of sites, each field split by column parity: `[even columns, odd columns]`.
#[derive(Default)]
pub(super) struct SplitRow {
    pub(super) albedo: [Vec<f32>; 2],
    pub(super) log: [Vec<f32>; 2],
    pub(super) normal: [[Vec<f32>; 3]; 2],
}

impl SplitRow {
    /// Fills this row from `sites` (one row of them) and their `logs`.
    pub(super) fn fill(&mut self, sites: &[SiteFit], logs: &[f32]) {
        assert_eq!(sites.len(), logs.len(), "a log per site");
        for parity in 0..2 {
            // Each field from its own slice: stepping a zip of the two (`zip().skip()
            // .step_by(2)`) advanced it one item at a time, a tenth of the demosaic's CPU.
            let sites = sites.get(parity..).unwrap_or_default();
            let logs = logs.get(parity..).unwrap_or_default();
            fill_every_other(&mut self.albedo[parity], sites, |s| s.albedo);
            fill_every_other(&mut self.log[parity], logs, |&l| l);
            for axis in 0..3 {
                fill_every_other(&mut self.normal[parity][axis], sites, |s| s.normal[axis]);
            }
        }
    }
}

/// `out` becomes `field` of every other item of `items`, from the first.
fn fill_every_other<T>(out: &mut Vec<f32>, items: &[T], field: impl Fn(&T) -> f32) {
    out.clear();
    out.extend(items.iter().step_by(2).map(field));
}

/// Per neighbour direction, each pixel's candidate: the continuity `change`, the `ratio` the
/// direction gives and the neighbour's own reflectance (for the plain mean).
#[derive(Default)]
pub(super) struct Candidates {
    change: [Vec<f32>; 4],
    ratio: [Vec<f32>; 4],
    neighbour: [Vec<f32>; 4],
}

/// The interior columns of a row at `parity`: pixels `x = parity + 2 j` with `2 <= x < w - 2`
/// (their neighbours up to two columns away need no mirroring), as a range of `j`.
pub(super) fn interior_run(w: usize, parity: usize) -> std::ops::Range<usize> {
    1..(w + 1 - parity).saturating_sub(2) / 2
}

/// The ratios of `channel` to the own channel at the interior pixels of `parity` in row `y`,
/// written into `plane` (the row of that channel's plane). `rows[2 + dy]` is row `y + dy`
/// split ([`SplitRow`]); `y` and the row's ends must be at least two sites from the border.
pub(super) fn ratios_of_run(
    pattern: [[u8; 2]; 2],
    y: usize,
    parity: usize,
    channel: u8,
    rows: [&SplitRow; 5],
    candidates: &mut Candidates,
    plane: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked above).
        return unsafe { ratios_of_run_avx2(pattern, y, parity, channel, rows, candidates, plane) };
    }
    ratios_of_run_portable(pattern, y, parity, channel, rows, candidates, plane)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn ratios_of_run_avx2(
    pattern: [[u8; 2]; 2],
    y: usize,
    parity: usize,
    channel: u8,
    rows: [&SplitRow; 5],
    candidates: &mut Candidates,
    plane: &mut [f32],
) {
    ratios_of_run_portable(pattern, y, parity, channel, rows, candidates, plane)
}

#[inline(always)]
fn ratios_of_run_portable(
    pattern: [[u8; 2]; 2],
    y: usize,
    parity: usize,
    channel: u8,
    rows: [&SplitRow; 5],
    candidates: &mut Candidates,
    plane: &mut [f32],
) {
    let w = plane.len();
    let run = interior_run(w, parity);
    if run.is_empty() {
        return;
    }
    let offsets = neighbours_of_channel(pattern, parity, y, channel);
    for (d, &(dx, dy)) in offsets.iter().enumerate() {
        direction(rows, parity, (dx, dy), run.clone(), candidates, d);
    }
    let n = offsets.len();
    let own = &rows[2].albedo[parity][run.clone()];
    for (k, &own) in own.iter().enumerate() {
        let x = parity + 2 * (run.start + k);
        plane[x] = if n == 4 {
            combine::<4>(candidates, k, own)
        } else {
            combine::<2>(candidates, k, own)
        };
    }
}

/// Each pixel's candidate from the neighbour at `(dx, dy)`, into `candidates`' slot `d`:
/// `ratio_along`'s first loop, branch-free.
#[inline(always)]
fn direction(
    rows: [&SplitRow; 5],
    parity: usize,
    (dx, dy): (isize, isize),
    run: std::ops::Range<usize>,
    candidates: &mut Candidates,
    d: usize,
) {
    // The neighbour's column parity and how far its split index is from the pixel's.
    let q = (parity as isize + dx).rem_euclid(2) as usize;
    let shift = (parity as isize + dx - q as isize) / 2;
    let len = run.len();
    let at = |start: usize, by: isize| (start as isize + by) as usize;
    let (own_row, far_row, near_row) = (
        rows[2],
        rows[(2 + 2 * dy) as usize],
        rows[(2 + dy) as usize],
    );
    let own = &own_row.albedo[parity][run.clone()];
    let own_log = &own_row.log[parity][run.clone()];
    let own_n = own_row.normal[parity].each_ref().map(|v| &v[run.clone()]);
    let far = at(run.start, dx)..at(run.start, dx) + len;
    let beyond = &far_row.albedo[parity][far.clone()];
    let beyond_log = &far_row.log[parity][far];
    let near = at(run.start, shift)..at(run.start, shift) + len;
    let neighbour = &near_row.albedo[q][near.clone()];
    let n = near_row.normal[q].each_ref().map(|v| &v[near.clone()]);
    // Slices of exactly `len`, not the vectors themselves: indexing a `Vec` in the loop
    // reloaded its pointer and length at every element and kept the loop scalar (a third of
    // the demosaic's CPU at 16 MP); over slices of one known length it vectorises.
    let change = resized(&mut candidates.change[d], len);
    let ratio = resized(&mut candidates.ratio[d], len);
    let neighbour_out = resized(&mut candidates.neighbour[d], len);
    let (own, own_log, beyond, beyond_log, neighbour) = (
        &own[..len],
        &own_log[..len],
        &beyond[..len],
        &beyond_log[..len],
        &neighbour[..len],
    );
    let (own_n, n) = (own_n.map(|v| &v[..len]), n.map(|v| &v[..len]));
    for k in 0..len {
        let cos = own_n[0][k] * n[0][k] + own_n[1][k] * n[1][k] + own_n[2][k] * n[2][k];
        let step = beyond_log[k] - own_log[k];
        let continued = continuity_change(step, cos);
        change[k] = if beyond[k] > 0.0 {
            continued
        } else {
            f32::INFINITY
        };
        let flank = if step.abs() < FLANK_CONTINUES {
            0.5 * (own[k] + beyond[k])
        } else {
            own[k]
        };
        ratio[k] = neighbour[k] / flank;
        neighbour_out[k] = neighbour[k];
    }
}

/// `v` resized to `len` values, as a slice.
#[inline(always)]
fn resized(v: &mut Vec<f32>, len: usize) -> &mut [f32] {
    v.resize(len, 0.0);
    &mut v[..len]
}

/// Pixel `k`'s ratio from its `N` candidates: `ratio_along`'s second half, branch-free (both
/// the plain mean and the weighted one are computed; a weight past the cut-off is 0).
#[inline(always)]
fn combine<const N: usize>(candidates: &Candidates, k: usize, own: f32) -> f32 {
    let change: [f32; N] = std::array::from_fn(|d| candidates.change[d][k]);
    let ratio: [f32; N] = std::array::from_fn(|d| candidates.ratio[d][k]);
    let neighbour: [f32; N] = std::array::from_fn(|d| candidates.neighbour[d][k]);
    let best = change.iter().fold(f32::INFINITY, |best, &c| best.min(c));
    let plain = neighbour.iter().sum::<f32>() / N as f32 / own;
    let (mut sum, mut weights) = (0.0f32, 0.0f32);
    for d in 0..N {
        let excess = (change[d] - best) / (CONTINUITY_SCALE * CONTINUITY_SCALE);
        // A weight of exactly 0 adds exactly nothing (the ratios are finite).
        let weight = if excess < 30.0 { exp_neg(excess) } else { 0.0 };
        sum += weight * ratio[d];
        weights += weight;
    }
    let ratio = if best.is_finite() {
        sum / weights
    } else {
        plain
    };
    if own > 0.0 {
        ratio
    } else {
        0.0
    }
}
