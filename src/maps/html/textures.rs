//! The relight's textures, which are also the page's display-size albedo and normal views:
//! block means of the full-resolution maps over their solved pixels.

use image::RgbImage;
use rayon::prelude::*;

use super::full_maps::{AlbedoMap, FullMaps, SOLVED};
use super::images::{byte, Reduction};
use super::relight::{linear_to_srgb8, RelightTextures};

/// One display row's full-resolution pixels (the `factor` rows of its blocks, one run of
/// pixels), read once: whether each is solved and its display albedo; with the per-block sums.
#[derive(Default)]
struct BlockRows {
    solved: Vec<bool>,
    albedo: [Vec<f32>; 3],
    sums: Vec<([f64; 3], [f64; 3], usize)>,
}

impl BlockRows {
    /// Reads display row `y`'s pixels; returns the index of the first.
    fn fill(&mut self, maps: &FullMaps, albedo: &AlbedoMap, r: &Reduction, y: usize) -> usize {
        let w = maps.width;
        let (y0, y1) = (y * r.factor, ((y + 1) * r.factor).min(maps.height));
        let (base, len) = (y0 * w, (y1 - y0) * w);
        self.solved.clear();
        match maps.status() {
            Some(status) => self
                .solved
                .extend(status[base..base + len].iter().map(|&s| s == SOLVED)),
            None => self.solved.resize(len, true),
        }
        for channel in &mut self.albedo {
            channel.resize(len, 0.0);
        }
        let [r, g, b] = &mut self.albedo;
        albedo.run_into(base, [&mut r[..len], &mut g[..len], &mut b[..len]]);
        base
    }
}

/// The relight's textures (also the page's albedo and normal views): block means over solved
/// pixels, the normal renormalised, unsolved blocks black (z < 0: no normal).
pub fn relight_textures(maps: &FullMaps, r: &Reduction) -> Option<RelightTextures> {
    let (albedo, normal) = (maps.albedo.as_ref()?, maps.normal.as_ref()?);
    let (w, h) = (maps.width, maps.height);
    // Per block: the albedo and normal sums and the solved pixels counted.
    type Sums = ([f64; 3], [f64; 3], usize);
    let pixel = |(a, n, count): &Sums| {
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if *count == 0 || len == 0.0 || !len.is_finite() {
            ([0u8; 3], [0u8; 3])
        } else {
            (
                a.map(|v| linear_to_srgb8((v / *count as f64) as f32)),
                n.map(|v| byte(((v / len) * 0.5 + 0.5) as f32)),
            )
        }
    };
    let row_bytes = r.width * 3;
    let mut a_data = vec![0u8; row_bytes * r.height];
    let mut n_data = vec![0u8; row_bytes * r.height];
    if row_bytes > 0 {
        a_data
            .par_chunks_mut(row_bytes)
            .zip(n_data.par_chunks_mut(row_bytes))
            .enumerate()
            .for_each_init(BlockRows::default, |rows, (y, (a_row, n_row))| {
                // The block row's pixels, read once in runs (a pixel at a time, through the
                // albedo's variant and the solved test, the block means took 0.14 s at 16 MP).
                let base = rows.fill(maps, albedo, r, y);
                let add = |(a, n, count): &mut Sums, i: usize| {
                    let j = i - base;
                    if rows.solved[j] {
                        for c in 0..3 {
                            a[c] += rows.albedo[c][j] as f64;
                            n[c] += normal[c].data[i] as f64;
                        }
                        *count += 1;
                    }
                };
                let sums = &mut rows.sums;
                sums.clear();
                sums.resize(r.width, ([0f64; 3], [0f64; 3], 0usize));
                r.sum_row((w, h), y, sums, add);
                for (x, block) in sums.iter().enumerate() {
                    let (a, n) = pixel(block);
                    a_row[x * 3..x * 3 + 3].copy_from_slice(&a);
                    n_row[x * 3..x * 3 + 3].copy_from_slice(&n);
                }
            });
    }
    let image = |data| RgbImage::from_raw(r.width as u32, r.height as u32, data);
    let (a_img, n_img) = (image(a_data)?, image(n_data)?);
    Some(RelightTextures {
        albedo: a_img,
        normal: n_img,
    })
}
