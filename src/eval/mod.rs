//! Comparing a solve with ground truth (synthetic sets, benchmark scenes): angular error of
//! the normals and relative error of the albedo, as summary statistics; and the real-data
//! evaluation behind `psscan eval` (`run`: estimators on light subsets of sets with ground
//! truth, `table`: its Markdown, JSON and plot).

mod anchors;
mod run;
mod subsets;
pub mod table;
mod trimmed;

pub use crate::math::angle_deg;
pub use run::{evaluate, EvalOptions, EvalReport, EvalSet, Row};

use nalgebra::Vector3;
use serde::Serialize;

use crate::math::select::{select, Orderable};
use crate::plane::Plane;
use crate::solve::{PixelStatus, SolveResult};

/// Mean, median, 95th percentile and maximum of a set of values.
#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct Stats {
    /// Arithmetic mean.
    pub mean: f64,
    /// Median (the value at sorted position `round((n - 1) / 2)`).
    pub median: f64,
    /// 95th percentile (the value at sorted position `round(0.95 (n - 1))`).
    pub p95: f64,
    /// Largest value.
    pub max: f64,
}

impl Stats {
    /// The statistics of `values` (reordered in place by the selection); all zero when empty.
    pub fn of(values: &mut [f64]) -> Stats {
        if values.is_empty() {
            return Stats::default();
        }
        // Order statistics by selection, not a full sort: tens of millions of values at 16 MP.
        let n = values.len();
        let mean = values.iter().sum::<f64>() / n as f64;
        let at = |q: f64| quantile_position(n, q);
        let [median, p95, max] =
            order_statistics(values, [at(0.5), at(0.95), n - 1], f64::total_cmp);
        Stats {
            mean,
            median,
            p95,
            max,
        }
    }

    /// [`Stats::of`] on every core, leaving `values` as they are: for the tens of millions of
    /// per-pixel errors of a 16 MP solve. The same order statistics; the mean is summed block
    /// by block, so it may differ from [`Stats::of`]'s in the last digits of a double.
    pub fn of_parallel(values: &[f64]) -> Stats {
        Stats::by_selection(values.len(), |i| Some(values[i]))
    }

    /// The statistics of the values `value(i)` gives for `i` in `0..n`, never stored
    /// ([`select`]): the order statistics [`Stats::of`] finds in a vector of
    /// them, the mean summed block by block.
    fn by_selection<T: Orderable>(n: usize, value: impl Fn(usize) -> Option<T> + Sync) -> Stats {
        let positions = |n: usize| [quantile_position(n, 0.5), quantile_position(n, 0.95), n - 1];
        match select(n, value, positions) {
            None => Stats::default(),
            Some(s) => Stats {
                mean: s.sum / s.count as f64,
                median: s.at[0].wide(),
                p95: s.at[1].wide(),
                max: s.at[2].wide(),
            },
        }
    }
}

/// The values at ascending sorted positions `at` (as if `values` were sorted), by selection:
/// each selection leaves the larger values above its position, so the next one searches only
/// those.
fn order_statistics<T: Copy + Default, const K: usize>(
    values: &mut [T],
    at: [usize; K],
    cmp: impl Fn(&T, &T) -> std::cmp::Ordering + Copy,
) -> [T; K] {
    let mut out = [T::default(); K];
    let mut rest: &mut [T] = values;
    let mut offset = 0;
    let mut last = None;
    for (k, &i) in at.iter().enumerate() {
        if let Some((j, v)) = last.filter(|&(j, _)| j == i) {
            out[k] = v;
            last = Some((j, v));
            continue;
        }
        let (_, v, above) = std::mem::take(&mut rest).select_nth_unstable_by(i - offset, cmp);
        out[k] = *v;
        last = Some((i, *v));
        offset = i + 1;
        rest = above;
    }
    out
}

/// How a solve compares with a synthetic set's ground truth, over the pixels it solved.
#[derive(Clone, Debug, Serialize)]
pub struct TruthComparison {
    /// Solved pixels compared.
    pub pixels: usize,
    /// Angle between solved and true normals, in degrees, over solved pixels.
    pub normal_error_deg: Stats,
    /// `|albedo - true| / true`, per channel, over solved pixels.
    pub albedo_rel_error: Stats,
}

/// Per-pixel angular error (degrees) of the solved normals; `None` where not solved.
pub fn normal_errors_deg(result: &SolveResult, truth: &[Plane; 3]) -> Vec<Option<f64>> {
    use rayon::prelude::*;
    (0..result.status.len())
        .into_par_iter()
        .map(|i| (result.status[i] == PixelStatus::Solved).then(|| error_at(result, truth, i)))
        .collect()
}

/// The angle (degrees) between pixel `i`'s solved normal and `truth`'s.
fn error_at(result: &SolveResult, truth: &[Plane; 3], i: usize) -> f64 {
    angle_deg(&result.normal_at(i), &truth_at(truth, i))
}

/// Pixel `i` of a truth normal map.
fn truth_at(truth: &[Plane; 3], i: usize) -> Vector3<f64> {
    Vector3::new(
        truth[0].data[i] as f64,
        truth[1].data[i] as f64,
        truth[2].data[i] as f64,
    )
}

/// The angular errors (degrees) of the solved pixels' normals, in pixel order.
pub fn solved_normal_errors_deg(result: &SolveResult, truth: &[Plane; 3]) -> Vec<f64> {
    collect_kept(
        result.status.len(),
        |i| result.status[i] == PixelStatus::Solved,
        |i| error_at(result, truth, i),
    )
}

/// `value(i)` for every `i` in `0..n` that `kept(i)`, in order, computed in parallel. Counted
/// block by block first, then written straight into one vector: a parallel collect of a
/// filtered iterator gathers per-thread vectors and copies them into the result, at 16 MP a
/// second 128 MB of fresh pages.
fn collect_kept<T: Copy + Default + Send>(
    n: usize,
    kept: impl Fn(usize) -> bool + Sync,
    value: impl Fn(usize) -> T + Sync,
) -> Vec<T> {
    use rayon::prelude::*;
    const BLOCK: usize = 1 << 16;
    let block = |b: usize| b * BLOCK..((b + 1) * BLOCK).min(n);
    let counts: Vec<usize> = (0..n.div_ceil(BLOCK))
        .into_par_iter()
        .map(|b| block(b).filter(|&i| kept(i)).count())
        .collect();
    let mut out = vec![T::default(); counts.iter().sum()];
    let mut slices = Vec::with_capacity(counts.len());
    let mut rest = out.as_mut_slice();
    for &count in &counts {
        let (head, tail) = rest.split_at_mut(count);
        slices.push(head);
        rest = tail;
    }
    slices.into_par_iter().enumerate().for_each(|(b, slice)| {
        let values = block(b).filter(|&i| kept(i)).map(&value);
        for (slot, v) in slice.iter_mut().zip(values) {
            *slot = v;
        }
    });
    out
}

/// Compares a solve with ground-truth normal and albedo maps over the pixels it solved.
pub fn compare(result: &SolveResult, normal: &[Plane; 3], albedo: &[Plane; 3]) -> TruthComparison {
    let angles = solved_normal_errors_deg(result, normal);
    compare_with_errors(result, &angles, albedo)
}

/// [`compare`] from the solved pixels' normal errors already computed
/// ([`solved_normal_errors_deg`]). Both statistics on every core (at 16 MP the albedo errors
/// are 48 M values, selected without storing them).
pub fn compare_with_errors(
    result: &SolveResult,
    angles: &[f64],
    albedo: &[Plane; 3],
) -> TruthComparison {
    TruthComparison {
        pixels: angles.len(),
        normal_error_deg: Stats::of_parallel(angles),
        albedo_rel_error: albedo_error_stats(result, albedo),
    }
}

/// The statistics of the relative albedo error `|albedo - true| / true` of every channel of
/// every solved pixel whose true albedo is positive, each error in single precision (the
/// figures are reported to three digits). The order statistics are those [`Stats::of`] finds
/// in a vector of the errors; the mean is summed block by block, so it may differ from a sum
/// in pixel order in the last digits of a double.
fn albedo_error_stats(result: &SolveResult, albedo: &[Plane; 3]) -> Stats {
    let error = |j: usize| {
        let (i, c) = (j / 3, j % 3);
        let truth = albedo[c].data[i];
        (result.status[i] == PixelStatus::Solved && truth > 0.0).then(|| {
            let truth = truth as f64;
            ((result.albedo[c].data[i] as f64 - truth).abs() / truth) as f32
        })
    };
    Stats::by_selection(3 * result.status.len(), error)
}

/// The sorted position of quantile `q` among `n` values: `round(q (n - 1))`.
fn quantile_position(n: usize, q: f64) -> usize {
    ((n - 1) as f64 * q).round() as usize
}

/// Normals against a ground-truth normal map over an object mask, as photometric-stereo
/// benchmarks (DiLiGenT) report them.
#[derive(Clone, Debug, Serialize)]
pub struct MaskedNormalComparison {
    /// Mask pixels with a ground-truth normal.
    pub mask_pixels: usize,
    /// Of those, the solved ones.
    pub solved: usize,
    /// Over every mask pixel; an unsolved pixel counts with the normal its map holds, (0, 0, 1).
    /// This is the figure benchmark tables list.
    pub normal_error_deg: Stats,
    /// Over the solved mask pixels only.
    pub solved_normal_error_deg: Stats,
}

/// Compares solved normals with `truth` over the `true` pixels of `mask` (truth vectors of
/// zero length are skipped).
pub fn compare_normals_over_mask(
    result: &SolveResult,
    truth: &[Plane; 3],
    mask: &crate::plane::Mask,
) -> MaskedNormalComparison {
    let mut all = Vec::new();
    let mut solved = Vec::new();
    for i in 0..result.status.len() {
        let t = truth_at(truth, i);
        if !mask.data[i] || t.norm().is_nan() || t.norm() <= 0.0 {
            continue;
        }
        let angle = angle_deg(&result.normal_at(i), &t);
        all.push(angle);
        if result.status[i] == PixelStatus::Solved {
            solved.push(angle);
        }
    }
    MaskedNormalComparison {
        mask_pixels: all.len(),
        solved: solved.len(),
        normal_error_deg: Stats::of(&mut all),
        solved_normal_error_deg: Stats::of(&mut solved),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn albedo_error_stats_are_those_of_the_solved_pixels_channels_with_positive_truth() {
        // Over several blocks, with unsolved pixels and channels whose truth is 0.
        let (w, h) = (1000, 150);
        let mut result = SolveResult::new(w, h);
        let mut truth: [Plane; 3] = std::array::from_fn(|_| Plane::new(w, h, 0.0));
        for i in 0..w * h {
            if i % 7 != 3 {
                result.status[i] = PixelStatus::Solved;
            }
            for c in 0..3 {
                result.albedo[c].data[i] = ((i * (c + 3)) % 101) as f32 * 0.01;
                truth[c].data[i] = if (i + c) % 11 == 0 {
                    0.0
                } else {
                    ((i * (c + 5)) % 97 + 1) as f32 * 0.01
                };
            }
        }
        let mut want = Vec::new();
        for i in 0..w * h {
            for c in 0..3 {
                let t = truth[c].data[i] as f64;
                if result.status[i] == PixelStatus::Solved && t > 0.0 {
                    want.push(((result.albedo[c].data[i] as f64 - t).abs() / t) as f32 as f64);
                }
            }
        }
        assert!(want.len() > 300_000, "{}", want.len());
        let got = albedo_error_stats(&result, &truth);
        let want = Stats::of(&mut want);
        assert_eq!(
            (got.median, got.p95, got.max),
            (want.median, want.p95, want.max)
        );
        assert!(
            (got.mean - want.mean).abs() <= 1e-12 * want.mean,
            "{got:?} {want:?}"
        );
        // The solve's normal errors: the solved pixels', in pixel order.
        let normal: [Plane; 3] = std::array::from_fn(|c| Plane::new(w, h, (c == 2) as u8 as f32));
        let errors = solved_normal_errors_deg(&result, &normal);
        let want: Vec<f64> = (0..w * h)
            .filter(|&i| result.status[i] == PixelStatus::Solved)
            .map(|i| error_at(&result, &normal, i))
            .collect();
        assert_eq!(errors, want);
    }

    #[test]
    fn stats_of_a_known_list() {
        let mut v: Vec<f64> = (1..=101).map(|x| x as f64).collect();
        let s = Stats::of(&mut v);
        assert_eq!((s.mean, s.median, s.p95, s.max), (51.0, 51.0, 96.0, 101.0));
        assert_eq!(Stats::of(&mut []), Stats::default());
    }

    #[test]
    fn stats_by_selection_equal_the_sorted_order_statistics() {
        // Shuffled values with repeats, and the short lists where quantiles coincide.
        for n in [1usize, 2, 3, 7, 20, 1000] {
            let mut v: Vec<f64> = (0..n).map(|i| ((i * 7919) % 97) as f64 * 0.5).collect();
            let mut sorted = v.clone();
            sorted.sort_by(|a, b| a.total_cmp(b));
            let at = |q: f64| sorted[((n - 1) as f64 * q).round() as usize];
            let s = Stats::of(&mut v);
            assert_eq!(
                (s.median, s.p95, s.max),
                (at(0.5), at(0.95), sorted[n - 1]),
                "{n}"
            );
            let mean = sorted.iter().sum::<f64>() / n as f64;
            assert!((s.mean - mean).abs() <= 1e-12 * mean.abs().max(1.0), "{n}");
            let p = Stats::of_parallel(&v);
            assert_eq!((p.median, p.p95, p.max), (s.median, s.p95, s.max), "{n}");
            assert!((p.mean - mean).abs() <= 1e-12 * mean.abs().max(1.0), "{n}");
        }
        assert_eq!(Stats::of_parallel(&[]), Stats::default());
    }
}
