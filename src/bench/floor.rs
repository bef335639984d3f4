//! The memory-read floor: the time it takes merely to read a solve's input planes once, with
//! the same threads and the same row-parallel split the solver uses. No solver reading every
//! input can beat it.

use rayon::prelude::*;

use crate::plane::Frames;

/// Bytes of decoded input the solve reads: every colour plane (`f32`, or 16-bit DN) and
/// saturation mask.
pub fn input_bytes(frames: &Frames) -> usize {
    frames
        .lights
        .iter()
        .map(|f| {
            f.rgb.channels().iter().map(|p| p.len()).sum::<usize>() * std::mem::size_of::<f32>()
                + f.dn
                    .as_ref()
                    .map_or(0, |d| d.dn.iter().map(Vec::len).sum::<usize>() * 2)
                + f.cfa_dn.as_ref().map_or(0, |d| d.dn.len() * 2)
                + f.saturated.as_ref().map_or(0, |m| m.data.len())
        })
        .sum()
}

/// Reads every input plane once (rows in parallel, each row summing all planes), returning
/// the sum so the reads cannot be optimised away.
pub fn read_all(frames: &Frames) -> f64 {
    let w = frames.width;
    (0..frames.height)
        .into_par_iter()
        .map(|y| {
            let mut acc = [0f32; 16];
            let mut count = 0usize;
            for f in &frames.lights {
                // A CFA frame's empty R and B planes hold nothing to read.
                for plane in f.rgb.channels().into_iter().filter(|p| !p.data.is_empty()) {
                    sum_row(&plane.data[y * w..(y + 1) * w], &mut acc);
                }
                let cfa_dn = f.cfa_dn.iter().map(|d| &d.dn);
                for dn in f.dn.iter().flat_map(|d| &d.dn).chain(cfa_dn) {
                    let sum: u32 = dn[y * w..(y + 1) * w].iter().map(|&v| v as u32).sum();
                    acc[0] += sum as f32;
                }
                if let Some(m) = &f.saturated {
                    count += m.data[y * w..(y + 1) * w].iter().filter(|&&b| b).count();
                }
            }
            acc.iter().map(|&v| v as f64).sum::<f64>() + count as f64
        })
        .sum()
}

/// Sums a row into 16 independent accumulators (vectorised, bound by memory, not by adds).
#[inline]
fn sum_row(row: &[f32], acc: &mut [f32; 16]) {
    let mut chunks = row.chunks_exact(16);
    for c in &mut chunks {
        for l in 0..16 {
            acc[l] += c[l];
        }
    }
    for (l, v) in chunks.remainder().iter().enumerate() {
        acc[l] += v;
    }
}
