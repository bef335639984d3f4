//! Order statistics of tens of millions of computed values, on every core and without storing
//! them: the percentiles of a 16 MP map's per-pixel figures (the report page's colour scales,
//! the errors against a synthetic set's truth). Selecting in a vector of the values costs a
//! vector of them (190 MB for 48 M albedo errors, all of it fresh memory) and a selection pass
//! over all of it on one core; here the values are counted and a few computed again instead.
//!
//! How: each value (`f32` or `f64`) has an unsigned key in `total_cmp`'s order. The first pass
//! counts the values by their key's top 16 bits (a histogram, block by block in parallel); the
//! counts name the bucket that holds each wanted position. The second pass gathers only the
//! values in those buckets and selects among them. The result is exactly what
//! `select_nth_unstable_by(k, total_cmp)` finds in a vector of all the values: values with one
//! key have one bit pattern. The first pass also keeps each index's bucket (two bytes, a
//! quarter of an `f64` value), so the second computes again only the values of the wanted
//! buckets, a few percent of them: the second pass had cost as much as the first (48 M
//! relative albedo errors, each a division).

use rayon::prelude::*;

/// Indices per block: each block of the first pass fills a histogram of its own.
const BLOCK: usize = 1 << 20;

/// Buckets of the first pass: the key's top 16 bits.
const BUCKETS: usize = 1 << 16;

/// A value type [`select`] orders: its key in `total_cmp`'s order, and its value as `f64`.
pub trait Orderable: Copy + Send + Sync {
    /// The top 16 bits of the key: negative values with their bits flipped below the
    /// positive ones, whose sign bit is set.
    fn bucket(self) -> usize;
    /// `total_cmp`.
    fn order(&self, other: &Self) -> std::cmp::Ordering;
    /// The value in double precision, for the sum.
    fn wide(self) -> f64;
}

impl Orderable for f32 {
    fn bucket(self) -> usize {
        let bits = self.to_bits();
        let key = if bits >> 31 == 1 {
            !bits
        } else {
            bits | 1 << 31
        };
        (key >> 16) as usize
    }
    fn order(&self, other: &Self) -> std::cmp::Ordering {
        self.total_cmp(other)
    }
    fn wide(self) -> f64 {
        self as f64
    }
}

impl Orderable for f64 {
    fn bucket(self) -> usize {
        let bits = self.to_bits();
        let key = if bits >> 63 == 1 {
            !bits
        } else {
            bits | 1 << 63
        };
        (key >> 48) as usize
    }
    fn order(&self, other: &Self) -> std::cmp::Ordering {
        self.total_cmp(other)
    }
    fn wide(self) -> f64 {
        self
    }
}

/// The count, the sum (in double precision, block by block, so the same on every run) and
/// the values at chosen sorted positions of the values `value(i)` gives for `i` in `0..n`
/// (`None`: no value at `i`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Selected<T, const K: usize> {
    /// How many values there are.
    pub count: usize,
    /// Their sum.
    pub sum: f64,
    /// The values at the positions asked for, in the order asked.
    pub at: [T; K],
}

/// The values that `value(i)` gives for `i` in `0..n`, counted and summed, and those at the
/// ascending sorted positions (by `total_cmp`) that `positions` names given the count;
/// `None` when there is no value. `value` is called once per index, and again for the indices
/// whose values fall in the buckets of the wanted positions, from several threads.
///
/// # Panics
/// When `positions` names a position at or past the count.
pub fn select<T: Orderable, const K: usize>(
    n: usize,
    value: impl Fn(usize) -> Option<T> + Sync,
    positions: impl FnOnce(usize) -> [usize; K],
) -> Option<Selected<T, K>> {
    let blocks = n.div_ceil(BLOCK);
    let block_range = |b: usize| b * BLOCK..((b + 1) * BLOCK).min(n);
    // Pass 1: how many values fall in each bucket, their sum, and each index's bucket (0 where
    // there is no value: bucket 0 also holds real values, so pass 2 checks again there).
    let partials: Vec<(Vec<u32>, f64, Vec<u16>)> = (0..blocks)
        .into_par_iter()
        .map(|b| {
            let mut counts = vec![0u32; BUCKETS];
            let mut sum = 0.0f64;
            let keys = block_range(b)
                .map(|i| match value(i) {
                    Some(v) => {
                        let bucket = v.bucket();
                        counts[bucket] += 1;
                        sum += v.wide();
                        bucket as u16
                    }
                    None => 0,
                })
                .collect();
            (counts, sum, keys)
        })
        .collect();
    let mut counts = vec![0usize; BUCKETS];
    let mut sum = 0.0;
    for (block_counts, block_sum, _) in &partials {
        for (total, &c) in counts.iter_mut().zip(block_counts) {
            *total += c as usize;
        }
        sum += block_sum;
    }
    let count: usize = counts.iter().sum();
    if count == 0 {
        return None;
    }
    // Which bucket holds each wanted position, and where in it.
    let wanted = positions(count);
    let mut starts = Vec::with_capacity(BUCKETS);
    let mut before = 0;
    for &c in &counts {
        starts.push(before);
        before += c;
    }
    let located: [(usize, usize); K] = wanted.map(|k| {
        assert!(k < count, "position {k} of {count} values");
        let b = starts.partition_point(|&s| s <= k) - 1;
        (b, k - starts[b])
    });
    let mut targets: Vec<usize> = located.iter().map(|&(b, _)| b).collect();
    targets.sort_unstable();
    targets.dedup();
    // Each bucket's place among the targets plus one; 0: not a target.
    let mut target_of = vec![0u16; BUCKETS];
    for (t, &b) in targets.iter().enumerate() {
        target_of[b] = u16::try_from(t + 1).expect("fewer targets than buckets");
    }
    // Pass 2: the values of those buckets (computed again, only there), gathered per bucket;
    // then a selection in each.
    let gathered: Vec<Vec<Vec<T>>> = (partials.into_par_iter().enumerate())
        .map(|(b, (_, _, keys))| {
            let mut per_target = vec![Vec::new(); targets.len()];
            for (i, key) in block_range(b).zip(keys) {
                let t = target_of[key as usize];
                if t > 0 {
                    if let Some(v) = value(i) {
                        per_target[t as usize - 1].push(v);
                    }
                }
            }
            per_target
        })
        .collect();
    let mut members: Vec<Vec<T>> = (0..targets.len())
        .map(|t| gathered.iter().flat_map(|g| g[t].iter().copied()).collect())
        .collect();
    let at = located.map(|(b, offset)| {
        let t = targets.binary_search(&b).expect("a target bucket");
        *members[t].select_nth_unstable_by(offset, T::order).1
    });
    Some(Selected { count, sum, at })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What a selection in a vector of all the values finds.
    fn by_sorting(values: &[Option<f32>], positions: &[usize]) -> Vec<f32> {
        let mut kept: Vec<f32> = values.iter().flatten().copied().collect();
        kept.sort_by(f32::total_cmp);
        positions.iter().map(|&k| kept[k]).collect()
    }

    #[test]
    fn selects_what_sorting_finds_over_several_blocks_with_gaps_ties_and_signs() {
        // Over three blocks: missing values, many repeats (one bucket holding a third of the
        // values), negative values, zeros of both signs, infinities and tiny magnitudes.
        let n = 2 * BLOCK + 12_345;
        let values: Vec<Option<f32>> = (0..n)
            .map(|i| match i % 11 {
                0 => None,
                1..=3 => Some(0.25),
                4 => Some(-((i % 977) as f32) * 0.013),
                5 => Some(if i % 2 == 0 { 0.0 } else { -0.0 }),
                6 if i % 1000 == 6 => Some(f32::INFINITY),
                6 => Some(1e-30 * (i % 313) as f32),
                _ => Some(((i * 7919) % 100_003) as f32 * 1e-3),
            })
            .collect();
        let count = values.iter().flatten().count();
        let got = select(
            n,
            |i| values[i],
            |c| [0, c / 3, c / 2, (c - 1) * 95 / 100, c - 1],
        )
        .unwrap();
        let want = by_sorting(
            &values,
            &[0, count / 3, count / 2, (count - 1) * 95 / 100, count - 1],
        );
        assert_eq!(got.count, count);
        for (g, w) in got.at.iter().zip(&want) {
            assert_eq!(g.to_bits(), w.to_bits(), "{:?} against {want:?}", got.at);
        }
        assert!(got.sum.is_infinite());
        // The same in double precision, with values that differ below f32's resolution.
        let wide: Vec<Option<f64>> = (values.iter().enumerate())
            .map(|(i, v)| v.map(|v| v as f64 + (i % 5) as f64 * 1e-12))
            .collect();
        let mut sorted: Vec<f64> = wide.iter().flatten().copied().collect();
        sorted.sort_by(f64::total_cmp);
        let at = [count / 7, count / 2, count - 2];
        let got = select(n, |i| wide[i], |_| at).unwrap();
        assert_eq!(got.at.map(f64::to_bits), at.map(|k| sorted[k].to_bits()));
    }

    #[test]
    fn a_wanted_value_in_bucket_zero_is_found_among_missing_values() {
        // Pass 1 marks a missing value with bucket 0, which is also the bucket of the lowest
        // keys (a NaN with every bit set): pass 2 must take the value there and skip the gaps.
        let lowest = f32::from_bits(u32::MAX);
        assert_eq!(lowest.bucket(), 0);
        let values: Vec<Option<f32>> = (0..1000)
            .map(|i| match i % 4 {
                0 => None,
                1 => Some(lowest),
                _ => Some(i as f32),
            })
            .collect();
        let count = values.iter().flatten().count();
        let at = [0, count / 4 - 1, count / 4, count - 1];
        let got = select(values.len(), |i| values[i], |_| at).unwrap();
        let want = by_sorting(&values, &at);
        assert_eq!(got.count, count);
        assert_eq!(
            got.at.map(f32::to_bits),
            [0, 1, 2, 3].map(|k| want[k].to_bits())
        );
    }

    #[test]
    fn counts_and_sums_finite_values_and_handles_none_and_one() {
        let values = [Some(3.0f32), None, Some(1.0), Some(2.0)];
        let got = select(4, |i| values[i], |c| [c / 2, c - 1]).unwrap();
        assert_eq!((got.count, got.sum, got.at), (3, 6.0, [2.0, 3.0]));
        assert_eq!(select::<f32, 1>(4, |_| None, |c| [c]), None);
        let one = select(1, |_| Some(-7.5), |_| [0, 0]).unwrap();
        assert_eq!(one.at, [-7.5, -7.5]);
    }
}
