//! The page's class legends count: how many pixels hold each status or fit class.

use super::full_maps::{FullMaps, SOLVED};

/// How many pixels of `classes` (a class plane's numbers) hold each class below `n` (the
/// solved ones only, with `solved_only`), counted on every core in blocks of plain loops over
/// slices (a fold over 16 M indexed values, moving its count vector through every step, took a
/// seventh of the page's time). Four counts per class, taken in turn: one count bumped by every
/// pixel waits on its own last store, and nearly every pixel is in the same class.
pub(super) fn class_counts(
    classes: &[u8],
    maps: &FullMaps,
    solved_only: bool,
    n: usize,
) -> Vec<usize> {
    use rayon::prelude::*;
    const BLOCK: usize = 1 << 16;
    let status = maps.status().filter(|_| solved_only);
    let count_block = |(b, values): (usize, &[u8])| {
        let mut counts = [[0usize; 256]; 4];
        let start = b * BLOCK;
        let mut count = |j: usize, v: u8, kept: bool| {
            counts[j % 4][v as usize] += kept as usize;
        };
        match status {
            Some(status) => {
                let status = &status[start..start + values.len()];
                for (j, (&v, &s)) in values.iter().zip(status).enumerate() {
                    count(j, v, s == SOLVED);
                }
            }
            None => {
                for (j, &v) in values.iter().enumerate() {
                    count(j, v, true);
                }
            }
        }
        let mut total = [0usize; 256];
        for part in &counts {
            total.iter_mut().zip(part).for_each(|(t, c)| *t += c);
        }
        total
    };
    let totals = classes
        .par_chunks(BLOCK)
        .enumerate()
        .map(count_block)
        .reduce(
            || [0usize; 256],
            |mut a, b| {
                a.iter_mut().zip(b).for_each(|(a, b)| *a += b);
                a
            },
        );
    totals[..n].to_vec()
}
