//! The page's images: the maps (`full_maps`) reduced to display size, colour-mapped, and
//! encoded (PNG where the page computes with the values, JPEG for the loupe's full-resolution
//! views) as `data:` URIs.

use image::{ImageEncoder, RgbImage};
use jpeg_encoder::SamplingFactor;
use rayon::prelude::*;

use super::full_maps::FullMaps;
use crate::math::select::select;
use crate::plane::Plane;

/// Longest side of the display-size maps (and the relight canvas).
pub const DISPLAY_MAX_SIDE: usize = 1024;

/// Integer reduction from full to display size.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct Reduction {
    /// Full-resolution pixels per display pixel along each axis (at least 1).
    pub factor: usize,
    /// Display width in pixels: the full width divided by `factor`, rounded up.
    pub width: usize,
    /// Display height in pixels: the full height divided by `factor`, rounded up.
    pub height: usize,
}

impl Reduction {
    /// The smallest whole factor that brings a `width x height` map's longer side within
    /// [`DISPLAY_MAX_SIDE`].
    pub fn for_size(width: usize, height: usize) -> Reduction {
        let factor = width.max(height).div_ceil(DISPLAY_MAX_SIDE).max(1);
        Reduction {
            factor,
            width: width.div_ceil(factor),
            height: height.div_ceil(factor),
        }
    }

    /// Adds every pixel of display row `y`'s blocks to its block's entry of `sums`
    /// (`add(&mut sums[x], i)` for each full-resolution pixel `i` of block `x`). Each block's
    /// pixels come row by row, left to right, as a block-by-block loop visits them, so each sum
    /// is the same to the bit; but the planes are read one full-resolution row after another,
    /// front to back. Block by block, `factor` rows of every plane were read at once in short
    /// pieces: at 16 MP the relight's block means took 0.35 s, 0.11 s row by row.
    ///
    /// A block's sum is added to in a local copy over the block's pixels of a row and stored
    /// back after them: added to in place, the compiler stored it to memory after every pixel
    /// and loaded it again for the next (a chain of store-to-load waits).
    #[inline(always)]
    pub(super) fn sum_row<A: Copy>(
        &self,
        (full_w, full_h): (usize, usize),
        y: usize,
        sums: &mut [A],
        mut add: impl FnMut(&mut A, usize),
    ) {
        let f = self.factor;
        let (y0, y1) = (y * f, ((y + 1) * f).min(full_h));
        for row in (y0..y1).map(|yy| yy * full_w) {
            for (x, sum) in sums.iter_mut().enumerate() {
                let (x0, x1) = (x * f, ((x + 1) * f).min(full_w));
                let mut local = *sum;
                for i in row + x0..row + x1 {
                    add(&mut local, i);
                }
                *sum = local;
            }
        }
    }
}

/// An RGB image of `width x height` whose row `y` (`3 * width` bytes) `fill(scratch, y, row)`
/// writes, rows in parallel, each thread with its own `scratch` (from `init`).
pub(super) fn par_image_rows<S>(
    width: usize,
    height: usize,
    init: impl Fn() -> S + Sync + Send,
    fill: impl Fn(&mut S, usize, &mut [u8]) + Sync + Send,
) -> RgbImage {
    let mut data = vec![0u8; width * height * 3];
    if width > 0 {
        data.par_chunks_mut(width * 3)
            .enumerate()
            .for_each_init(init, |scratch, (y, row)| fill(scratch, y, row));
    }
    RgbImage::from_raw(width as u32, height as u32, data).expect("the buffer fits the size")
}

pub(super) fn byte(v: f32) -> u8 {
    // Through `i32`, whose conversion vectorises (a saturating `as u8` from `f32` did not):
    // the same byte for every value in [0, 255], which the clamp leaves (NaN becomes 0).
    crate::math::round_non_negative(v.clamp(0.0, 1.0) * 255.0) as i32 as u8
}

/// A class map at display size: each block takes its most common class, `class_at(i)` being
/// pixel i's of the `w x h` full-resolution map (read through a function, so that a
/// caller masking some pixels copies no 16 MP plane to do it).
pub fn class_image(
    (w, h): (usize, usize),
    class_at: impl Fn(usize) -> u8 + Sync,
    r: &Reduction,
    colour: impl Fn(u8) -> [u8; 3] + Sync,
) -> RgbImage {
    let f = r.factor;
    // A display row's classes, block after block (`f * f` slots each, in the block's order),
    // and per class a count that only the block being decided has touched.
    let scratch = || {
        (
            vec![0u8; r.width * f * f],
            vec![(0usize, 0usize); r.width],
            [0u32; 256],
        )
    };
    par_image_rows(
        r.width,
        r.height,
        scratch,
        |(classes, blocks, counts), y, row| {
            for (x, block) in blocks.iter_mut().enumerate() {
                *block = (x * f * f, 0);
            }
            r.sum_row((w, h), y, blocks, |(start, len), i| {
                classes[*start + *len] = class_at(i);
                *len += 1;
            });
            for (px, &(start, len)) in row.chunks_exact_mut(3).zip(blocks.iter()) {
                // The winner is kept as the counts grow (a count only grows, so the running best
                // is the best so far): not a scan of all 256 classes per display pixel (at 16 MP
                // that scan was most of the report page's own time). Ties go to the lower class.
                let block = &classes[start..start + len];
                // Most blocks hold one class: that class wins without counting.
                if let Some(&first) = block.first() {
                    if block.iter().all(|&c| c == first) {
                        px.copy_from_slice(&colour(first));
                        continue;
                    }
                }
                let mut best = (0u32, std::cmp::Reverse(0u8));
                for &c in block {
                    counts[c as usize] += 1;
                    best = best.max((counts[c as usize], std::cmp::Reverse(c)));
                }
                for &c in block {
                    counts[c as usize] = 0;
                }
                px.copy_from_slice(&colour(best.1 .0));
            }
        },
    )
}

/// Viridis, sampled at nine points (matplotlib's table), linearly interpolated.
pub fn viridis(t: f32) -> [u8; 3] {
    const STOPS: [[u8; 3]; 9] = [
        [68, 1, 84],
        [71, 44, 122],
        [59, 81, 139],
        [44, 113, 142],
        [33, 144, 141],
        [39, 173, 129],
        [92, 200, 99],
        [170, 220, 50],
        [253, 231, 37],
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    } * 8.0;
    let i = (t.floor() as usize).min(7);
    let f = t - i as f32;
    std::array::from_fn(|c| {
        (STOPS[i][c] as f32 * (1.0 - f) + STOPS[i + 1][c] as f32 * f).round() as u8
    })
}

/// Colour of pixels a continuous map has no value for.
pub const NO_VALUE: [u8; 3] = [30, 30, 30];

/// The value range a colour scale spans: 0 to the 99th percentile over the solved pixels
/// (selected without gathering the values: 16 M of them at 16 MP).
pub fn scale_max(plane: &Plane, maps: &FullMaps) -> f32 {
    let value = |i: usize| Some(plane.data[i]).filter(|v| maps.solved(i) && v.is_finite());
    let p99 = |n: usize| [((n - 1) as f64 * 0.99) as usize];
    match select(plane.data.len(), value, p99) {
        Some(s) if s.at[0] > 0.0 => s.at[0],
        _ => 1.0,
    }
}

/// A continuous map at display size: block means over solved pixels, viridis over `[0, max]`.
pub fn scalar_image(plane: &Plane, maps: &FullMaps, r: &Reduction, max: f32) -> RgbImage {
    let (w, h) = (plane.width, plane.height);
    let add = |(sum, count): &mut (f64, usize), i: usize| {
        if maps.solved(i) && plane.data[i].is_finite() {
            *sum += plane.data[i] as f64;
            *count += 1;
        }
    };
    par_image_rows(r.width, r.height, Vec::new, |sums, y, row| {
        sums.clear();
        sums.resize(r.width, (0f64, 0usize));
        r.sum_row((w, h), y, sums, add);
        for (px, &(sum, count)) in row.chunks_exact_mut(3).zip(sums.iter()) {
            px.copy_from_slice(&if count == 0 {
                NO_VALUE
            } else {
                viridis((sum / count as f64) as f32 / max)
            });
        }
    })
}

/// The legend strip of [`viridis`], 256 x 12.
pub fn viridis_legend() -> RgbImage {
    RgbImage::from_fn(256, 12, |x, _| image::Rgb(viridis(x as f32 / 255.0)))
}

/// PNG bytes of an 8-bit RGB image.
pub fn png_bytes(img: &RgbImage) -> Vec<u8> {
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(
            img.as_raw(),
            img.width(),
            img.height(),
            image::ExtendedColorType::Rgb8,
        )
        .expect("encoding an in-memory RGB image cannot fail");
    out
}

/// The Huffman tables a JPEG is written with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HuffmanTables {
    /// The standard tables (JPEG's Annex K): one pass over the image's blocks.
    Standard,
    /// Tables fitted to the image's own symbols: a second pass over its blocks. On a 16 MP
    /// map's 8-bit view at quality 80 (jpeg-encoder 0.7), 2.6 % (albedo) and 4.2 % (normal)
    /// fewer bytes for 70 % more encode time.
    Optimised,
}

/// JPEG bytes of an 8-bit RGB image (optimised tables: these images are small).
pub fn jpeg_bytes(img: &RgbImage, quality: u8, chroma: SamplingFactor) -> Vec<u8> {
    let size = (img.width() as usize, img.height() as usize);
    jpeg_bytes_of(
        img.as_raw(),
        size,
        (quality, HuffmanTables::Optimised),
        chroma,
    )
}

/// JPEG bytes of `(width, height)` 8-bit RGB pixels, row by row, at `quality` with `tables`.
pub fn jpeg_bytes_of(
    pixels: &[u8],
    (width, height): (usize, usize),
    (quality, tables): (u8, HuffmanTables),
    chroma: SamplingFactor,
) -> Vec<u8> {
    let mut out = Vec::new();
    let mut encoder = jpeg_encoder::Encoder::new(&mut out, quality);
    encoder.set_sampling_factor(chroma);
    encoder.set_optimized_huffman_tables(tables == HuffmanTables::Optimised);
    encoder
        .encode(
            pixels,
            width as u16,
            height as u16,
            jpeg_encoder::ColorType::Rgb,
        )
        .expect("an in-memory RGB image under JPEG's 65535-pixel side always encodes");
    out
}

/// A `data:` URI of `bytes`, in standard base64 with padding (RFC 4648).
pub fn data_uri(mime: &str, bytes: &[u8]) -> String {
    use base64::Engine;
    let mut uri = format!("data:{mime};base64,");
    base64::engine::general_purpose::STANDARD.encode_string(bytes, &mut uri);
    uri
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::maps::html::full_maps::class_of;

    #[test]
    fn byte_rounds_as_f32_round_does() {
        let round = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        // (`math::round_non_negative`'s own test covers the rounding; this, the clamp.)
        // Every f32 within a few ulps of each tie between two bytes, and of each byte.
        let mut values = vec![f32::NAN, -1.0, -0.0, 0.0, 1.0, 2.0, f32::INFINITY];
        for k in 0..=256 {
            for centre in [(k as f32 - 0.5) / 255.0, k as f32 / 255.0] {
                let bits = centre.max(0.0).to_bits() as i64;
                values.extend((-8..=8).map(|d| f32::from_bits((bits + d).max(0) as u32)));
            }
        }
        values.extend((0..100_000).map(|i| i as f32 * 1.1e-5));
        for v in values {
            assert_eq!(byte(v), round(v), "{v:e}");
        }
    }

    #[test]
    fn data_uris_hold_rfc_4648_base64() {
        for (input, expected) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            let uri = data_uri("text/plain", input.as_bytes());
            assert_eq!(uri, format!("data:text/plain;base64,{expected}"));
        }
    }

    #[test]
    fn reduction_fits_the_display_side_and_covers_every_pixel() {
        let r = Reduction::for_size(4912, 3264);
        assert_eq!(r.factor, 5);
        assert!(r.width <= DISPLAY_MAX_SIDE && r.width * r.factor >= 4912);
        assert!(r.height * r.factor >= 3264);
        let r = Reduction::for_size(300, 200);
        assert_eq!((r.factor, r.width, r.height), (1, 300, 200));
    }

    #[test]
    fn class_blocks_take_the_most_common_class() {
        let plane = Plane::from_vec(2, 2, vec![0.0, 2.0, 2.0, 5.0]).unwrap();
        let r = Reduction {
            factor: 2,
            width: 1,
            height: 1,
        };
        let img = class_image((2, 2), |i| class_of(plane.data[i]), &r, |c| [c, 0, 0]);
        assert_eq!(img.get_pixel(0, 0).0, [2, 0, 0]);
    }

    /// Every block's pixels, a block at a time: the reference the row-by-row reduction must
    /// equal.
    fn block_pixels(r: &Reduction, (w, h): (usize, usize), (x, y): (usize, usize)) -> Vec<usize> {
        let f = r.factor;
        (y * f..((y + 1) * f).min(h))
            .flat_map(|yy| (x * f..((x + 1) * f).min(w)).map(move |xx| yy * w + xx))
            .collect()
    }

    #[test]
    fn row_by_row_block_reductions_equal_block_by_block_ones() {
        // 3 x 3 blocks that do not divide 17 x 11: the last column and row of blocks are
        // partial. Values of many magnitudes, so that a sum in another order would differ.
        let (w, h): (usize, usize) = (17, 11);
        let r = Reduction {
            factor: 3,
            width: w.div_ceil(3),
            height: h.div_ceil(3),
        };
        let value = |i: usize| ((i * 7919) % 97) as f32 * 10f32.powi((i % 9) as i32 - 4);
        let plane = Plane::from_vec(w, h, (0..w * h).map(value).collect()).unwrap();
        // Pixels with status 1 are unsolved: left out of the means.
        let status: Vec<u8> = (0..w * h).map(|i| (i % 5 == 0) as u8).collect();
        let maps = FullMaps::of_confidence(status.clone(), status, [plane.clone(), plane.clone()]);
        let max = 50.0;
        let scalar = scalar_image(&plane, &maps, &r, max);
        let class = |i: usize| ((plane.data[i] as usize) % 4) as u8;
        let classes = class_image((w, h), class, &r, |c| [c, 0, 0]);
        for y in 0..r.height {
            for x in 0..r.width {
                let pixels = block_pixels(&r, (w, h), (x, y));
                let solved: Vec<usize> =
                    pixels.iter().copied().filter(|&i| maps.solved(i)).collect();
                let sum: f64 = solved.iter().map(|&i| plane.data[i] as f64).sum();
                let mean = viridis((sum / solved.len() as f64) as f32 / max);
                assert_eq!(
                    scalar.get_pixel(x as u32, y as u32).0,
                    mean,
                    "block ({x}, {y})"
                );
                let mut counts = [0usize; 4];
                for &i in &pixels {
                    counts[(plane.data[i] as usize) % 4] += 1;
                }
                // The most common class, the lower one on a tie.
                let most = (0..4)
                    .max_by_key(|&c| (counts[c], std::cmp::Reverse(c)))
                    .unwrap();
                assert_eq!(classes.get_pixel(x as u32, y as u32).0, [most as u8, 0, 0]);
            }
        }
    }
}
