//! The loupe's sources: the albedo and normal maps at full resolution (or every n-th pixel)
//! as bands of JPEG rows, sized to what the page's budget leaves (the page draws a view's
//! bands into one canvas).

use image::RgbImage;
use jpeg_encoder::SamplingFactor;
use rayon::prelude::*;

use super::full_maps::{AlbedoMap, FullMaps};
use super::images::{self, byte, HuffmanTables};
use crate::plane::Plane;

/// JPEG qualities the loupe tries at each sampling, best first. The floor keeps block
/// artefacts below a thread's edge contrast; under it, resolution is given up instead.
const LOUPE_QUALITIES: [u8; 3] = [88, 80, 72];

/// Rows per band: each view is encoded as bands of this many rows, each its own JPEG, so
/// that the encodes share out over all cores (two whole views kept one core idle while the
/// slower normal view finished) and a size sample is a subset of the bands themselves. A
/// whole number of 4:2:0 blocks (16 rows), so the bands' blocks are the whole view's.
const LOUPE_BAND_ROWS: usize = 32;

/// One band in this many goes into the size sample.
const SAMPLE_EVERY: usize = 8;

/// A quality is skipped only when its predicted size is over the budget by more than this
/// factor (the prediction from a sample of bands is a few percent off either way).
const PREDICTION_MARGIN: f64 = 1.05;

/// Optimised Huffman tables save less than this share of the standard tables' bytes (2.6 %
/// and 4.2 % on a 16 MP solve's two views): a quality whose standard-table sample is further
/// over the budget than that is not sampled with optimised tables.
const OPTIMISED_TABLES_SAVE_UNDER: f64 = 0.1;

/// The encodings tried at each sampling, best first: each quality with the standard Huffman
/// tables, then, where those do not fit, with tables optimised for each band (70 % more
/// encode time for a few percent fewer bytes, which is what keeps a quality in the budget when
/// the standard tables miss it by a little). Where a whole standard encode misses by a little,
/// only its largest bands are encoded again with optimised tables
/// ([`top_up_with_optimised`]).
fn encodings() -> impl Iterator<Item = Encoding> {
    LOUPE_QUALITIES.into_iter().flat_map(|quality| {
        [HuffmanTables::Standard, HuffmanTables::Optimised].map(|tables| (quality, tables))
    })
}

/// A JPEG quality and the Huffman tables it is written with.
type Encoding = (u8, HuffmanTables);

/// One band of one view: the view's index in the sources and the band's first row.
type BandId = (usize, usize);

/// The loupe's views as JPEG bands: the finest sampling, then the best encoding
/// ([`encodings`]), that fits the budget.
fn loupe_views(maps: &FullMaps, budget: usize) -> Loupe {
    let mut step = 1;
    let last = encodings().last().expect("a quality to try");
    loop {
        let (albedo, normal) = full_views(maps, step);
        let sources: Vec<(&str, RgbImage)> = [("albedo", albedo), ("normal", normal)]
            .into_iter()
            .filter_map(|(name, img)| img.map(|i| (name, i)))
            .collect();
        let bands = band_ids(&sources);
        let mut base64_bytes = 0;
        let mut standard_predicted = 0;
        // The quality whose standard encode was topped up with optimised bands.
        let mut topped_up = None;
        for encoding in encodings() {
            if encoding.1 == HuffmanTables::Optimised && topped_up == Some(encoding.0) {
                // Every band of this quality was tried with optimised tables already.
                continue;
            }
            if encoding.1 == HuffmanTables::Optimised
                && encoding != last
                && standard_predicted as f64 * (1.0 - OPTIMISED_TABLES_SAVE_UNDER)
                    > budget as f64 * PREDICTION_MARGIN
            {
                // Optimised tables cannot bring this quality into the budget.
                continue;
            }
            // A full encode at 16 MP takes most of a second: an encoding whose sample says it
            // will not fit is skipped (the last one is always tried). The sample's bands are
            // kept for the whole encode when the encoding is taken.
            let sampled = if encoding != last && step < 16 {
                encode_bands(&sources, &sample_bands(&bands, &sources), encoding)
            } else {
                Vec::new()
            };
            if !sampled.is_empty() {
                let predicted = predicted_bytes(&sources, &sampled);
                if encoding.1 == HuffmanTables::Standard {
                    standard_predicted = predicted;
                }
                if predicted as f64 > budget as f64 * PREDICTION_MARGIN {
                    base64_bytes = predicted;
                    continue;
                }
            }
            let rest: Vec<BandId> = bands
                .iter()
                .filter(|id| !sampled.iter().any(|(done, _)| done == *id))
                .copied()
                .collect();
            let mut encoded = sampled;
            encoded.extend(encode_bands(&sources, &rest, encoding));
            encoded.sort_by_key(|(id, _)| *id);
            base64_bytes = base64_size(&encoded);
            if encoding.1 == HuffmanTables::Standard {
                standard_predicted = base64_bytes;
                if base64_bytes > budget && step < 16 {
                    // Over by a little (the sample said it would fit): optimised tables for
                    // as many bands as it takes, not a second encode of all of them.
                    base64_bytes =
                        top_up_with_optimised(&sources, &mut encoded, encoding.0, budget);
                    topped_up = Some(encoding.0);
                }
            }
            if base64_bytes <= budget || step >= 16 {
                let views = encoded
                    .into_iter()
                    .map(|((view, row), bytes)| LoupeBand {
                        view: sources[view].0.to_string(),
                        row,
                        bytes,
                    })
                    .collect();
                return Loupe {
                    step,
                    quality: encoding.0,
                    views,
                };
            }
        }
        // Bytes scale with pixels: jump straight to a step that should fit.
        let ratio = (base64_bytes as f64 / budget.max(1) as f64).sqrt();
        step = (step as f64 * ratio).ceil().max(step as f64 + 1.0) as usize;
    }
}

/// Every band of every source, view by view, top to bottom.
fn band_ids(sources: &[(&str, RgbImage)]) -> Vec<BandId> {
    let mut ids = Vec::new();
    for (view, (_, img)) in sources.iter().enumerate() {
        ids.extend(
            (0..img.height() as usize)
                .step_by(LOUPE_BAND_ROWS)
                .map(|row| (view, row)),
        );
    }
    ids
}

/// The size sample: every [`SAMPLE_EVERY`]-th band of each view; none for a view too small
/// to sample (fewer than four sampled bands: encoding it whole is cheap).
fn sample_bands(bands: &[BandId], sources: &[(&str, RgbImage)]) -> Vec<BandId> {
    let too_small = sources
        .iter()
        .any(|(_, img)| (img.height() as usize).div_ceil(LOUPE_BAND_ROWS) < 4 * SAMPLE_EVERY);
    if too_small {
        return Vec::new();
    }
    let every = SAMPLE_EVERY * LOUPE_BAND_ROWS;
    bands
        .iter()
        .filter(|(_, row)| row % every == 0)
        .copied()
        .collect()
}

/// Batches in which [`top_up_with_optimised`] re-encodes the bands: it stops at most one
/// batch (this share of the bands) past what the budget needs.
const TOP_UP_BATCHES: usize = 8;

/// The base64 bytes of `encoded`'s JPEGs.
fn base64_size(encoded: &[(BandId, Vec<u8>)]) -> usize {
    encoded.iter().map(|(_, jpeg)| jpeg.len() * 4 / 3).sum()
}

/// Re-encodes bands of `encoded` (all at `quality` with the standard tables) with optimised
/// tables, the largest first and a batch at a time, until the whole fits `budget` or every
/// band is done; a band keeps whichever of its two JPEGs is smaller. The decoded pixels do
/// not change (the tables code the same quantised blocks). Returns the new base64 size.
fn top_up_with_optimised(
    sources: &[(&str, RgbImage)],
    encoded: &mut [(BandId, Vec<u8>)],
    quality: u8,
    budget: usize,
) -> usize {
    let mut order: Vec<usize> = (0..encoded.len()).collect();
    order.sort_by_key(|&i| std::cmp::Reverse(encoded[i].1.len()));
    let batch = encoded.len().div_ceil(TOP_UP_BATCHES).max(1);
    for chunk in order.chunks(batch) {
        if base64_size(encoded) <= budget {
            break;
        }
        let ids: Vec<BandId> = chunk.iter().map(|&i| encoded[i].0).collect();
        let optimised = encode_bands(sources, &ids, (quality, HuffmanTables::Optimised));
        for (&i, (_, jpeg)) in chunk.iter().zip(optimised) {
            if jpeg.len() < encoded[i].1.len() {
                encoded[i].1 = jpeg;
            }
        }
    }
    base64_size(encoded)
}

/// JPEGs of the bands `ids`, encoded in parallel (one band per task).
fn encode_bands(
    sources: &[(&str, RgbImage)],
    ids: &[BandId],
    encoding: Encoding,
) -> Vec<(BandId, Vec<u8>)> {
    ids.par_iter()
        .map(|&(view, row)| {
            let (name, img) = &sources[view];
            let (w, h) = (img.width() as usize, img.height() as usize);
            let rows = LOUPE_BAND_ROWS.min(h - row);
            let pixels = &img.as_raw()[row * w * 3..(row + rows) * w * 3];
            let bytes = images::jpeg_bytes_of(pixels, (w, rows), encoding, chroma(name));
            ((view, row), bytes)
        })
        .collect()
}

/// The base64 bytes of all views predicted from the `sampled` bands' JPEGs, each view's
/// scaled by the rows its sample stands for.
fn predicted_bytes(sources: &[(&str, RgbImage)], sampled: &[(BandId, Vec<u8>)]) -> usize {
    let total: f64 = (0..sources.len())
        .map(|view| {
            let h = sources[view].1.height() as usize;
            let mine = sampled.iter().filter(|((v, _), _)| *v == view);
            let (rows, bytes) = mine.fold((0, 0), |(rows, bytes), ((_, row), jpeg)| {
                (rows + LOUPE_BAND_ROWS.min(h - row), bytes + jpeg.len())
            });
            bytes as f64 * h as f64 / rows.max(1) as f64 * 4.0 / 3.0
        })
        .sum();
    total as usize
}

/// Chroma sampling of a loupe view: the albedo's colour varies more slowly than its
/// brightness, as photographs' does (4:2:0); the normal map's colour is its X and Y, so it
/// keeps full vertical chroma resolution (4:2:2).
fn chroma(view: &str) -> SamplingFactor {
    if view == "albedo" {
        SamplingFactor::R_4_2_0
    } else {
        SamplingFactor::R_4_2_2
    }
}

/// One band of a loupe view: its first row and its JPEG.
struct LoupeBand {
    view: String,
    row: usize,
    bytes: Vec<u8>,
}

/// The loupe's sources: every `step`-th pixel, JPEG bands at `quality`, view by view, top
/// to bottom.
struct Loupe {
    step: usize,
    quality: u8,
    views: Vec<LoupeBand>,
}

/// The loupe's `<img>` tags, with its sampling step and JPEG quality (1 and 0 without maps).
pub(super) fn loupe_parts(maps: &FullMaps, budget: usize) -> (usize, u8, String) {
    if maps.albedo.is_none() || maps.normal.is_none() {
        return (1, 0, String::new());
    }
    let loupe = loupe_views(maps, budget);
    let tags = loupe
        .views
        .iter()
        .map(|band| {
            format!(
                "<img class=\"loupe-src\" data-view=\"{view}\" data-row=\"{row}\" alt=\"{view} at full resolution, rows from {row}\" src=\"{}\">",
                images::data_uri("image/jpeg", &band.bytes),
                view = band.view,
                row = band.row,
            )
        })
        .collect();
    (loupe.step, loupe.quality, tags)
}

/// Full-resolution 8-bit views for the loupe: sRGB albedo and the OpenGL normal encoding.
fn full_views(maps: &FullMaps, step: usize) -> (Option<RgbImage>, Option<RgbImage>) {
    let (w, h) = (maps.width.div_ceil(step), maps.height.div_ceil(step));
    rayon::join(
        || {
            maps.albedo.as_ref().map(|a| {
                // The table once, not per sample (`linear_to_srgb8` looks it up each call).
                let table = crate::maps::srgb::srgb8();
                albedo_view(a, maps.width, (w, h, step), |v| table.code(v) as u8)
            })
        },
        || {
            maps.normal.as_ref().map(|n| {
                let planes = n.each_ref().map(|p| &**p);
                sampled_view(planes, maps.width, (w, h, step), |v| byte(v * 0.5 + 0.5))
            })
        },
    )
}

/// Every `step`-th pixel of `planes` (rows `width` long) as a `w x h` image, each value through
/// `to_byte`. Generic in `to_byte` so that the conversion inlines: at 16 MP through a `dyn Fn`
/// it was a call per value, 48 million of them.
fn sampled_view(
    planes: [&Plane; 3],
    width: usize,
    (w, h, step): (usize, usize, usize),
    to_byte: impl Fn(f32) -> u8 + Sync,
) -> RgbImage {
    sampled_rows(
        |start, channels| {
            for (plane, channel) in planes.iter().zip(channels) {
                let row = &plane.data[start..start + width];
                // Every pixel (the loupe's first try, 16 MP at full resolution) without
                // `step_by`, whose iterator a loop does not vectorise through.
                if step == 1 {
                    channel.copy_from_slice(&row[..channel.len()]);
                } else {
                    channel
                        .iter_mut()
                        .zip(row.iter().step_by(step))
                        .for_each(|(c, &v)| *c = v);
                }
            }
        },
        width,
        (w, h, step),
        to_byte,
    )
}

/// [`sampled_view`] of the display albedo, read in runs at full resolution.
fn albedo_view(
    albedo: &AlbedoMap,
    width: usize,
    (w, h, step): (usize, usize, usize),
    to_byte: impl Fn(f32) -> u8 + Sync,
) -> RgbImage {
    sampled_rows(
        |start, [r, g, b]| {
            if step == 1 {
                albedo.run_into(start, [r, g, b]);
                return;
            }
            for (x, ((r, g), b)) in r.iter_mut().zip(g).zip(b).enumerate() {
                [*r, *g, *b] = albedo.pixel(start + x * step);
            }
        },
        width,
        (w, h, step),
        to_byte,
    )
}

/// A `w x h` image whose row `y` holds the values `values(start, channels)` puts in the three
/// channel rows (`start`: the index of the row's first sampled pixel), each through `to_byte`.
///
/// A row goes channel by channel, values, then bytes, then interleaved, each step a loop over
/// plain slices: converting and interleaving pixel by pixel, the compiler called the
/// conversion per pixel, not inlined, with a branch per value on its rounding (half of them
/// mispredicted); the 16 MP normal view took 0.22 s, more than the albedo's colour matrix
/// and sRGB table.
fn sampled_rows(
    values: impl Fn(usize, [&mut [f32]; 3]) + Sync,
    width: usize,
    (w, h, step): (usize, usize, usize),
    to_byte: impl Fn(f32) -> u8 + Sync,
) -> RgbImage {
    let scratch = || (vec![0f32; 3 * w], vec![0u8; 3 * w]);
    images::par_image_rows(w, h, scratch, |(floats, bytes), y, out| {
        let [r, g, b] = split3(floats);
        values(y * step * width, [r, g, b]);
        for (byte, &v) in bytes.iter_mut().zip(floats.iter()) {
            *byte = to_byte(v);
        }
        let (r, gb) = bytes.split_at(w);
        let (g, b) = gb.split_at(w);
        for (px, ((&r, &g), &b)) in out.chunks_exact_mut(3).zip(r.iter().zip(g).zip(b)) {
            px.copy_from_slice(&[r, g, b]);
        }
    })
}

/// A buffer of three equal rows as the three rows.
fn split3<T>(buffer: &mut [T]) -> [&mut [T]; 3] {
    let w = buffer.len() / 3;
    let (r, gb) = buffer.split_at_mut(w);
    let (g, b) = gb.split_at_mut(w);
    [r, g, b]
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::borrow::Cow;

    /// The albedo view of a solve in memory: each sampled pixel through the display matrix
    /// (in double precision), clamped, as its sRGB code; unsolved pixels black.
    #[test]
    fn the_albedo_view_of_a_solve_converts_each_sampled_pixel() {
        use crate::solve::{PixelStatus, SolveResult};
        let (w, h) = (23, 9);
        let mut result = SolveResult::new(w, h);
        for i in 0..w * h {
            for (c, plane) in result.albedo.iter_mut().enumerate() {
                plane.data[i] = ((i * 13 + c * 7) % 29) as f32 / 25.0 - 0.05;
            }
            if i % 4 != 1 {
                result.status[i] = PixelStatus::Solved;
            }
        }
        let matrix = [[1.6, -0.4, -0.2], [-0.2, 1.5, -0.3], [0.0, -0.5, 1.5]];
        let maps = FullMaps {
            width: w,
            height: h,
            albedo: Some(AlbedoMap::Solve {
                result: &result,
                display_matrix: Some(matrix),
            }),
            normal: Some(result.normal.each_ref().map(Cow::Borrowed)),
            confidence: None,
            missing: Vec::new(),
        };
        for step in [1, 2] {
            let albedo = full_views(&maps, step).0.unwrap();
            for (x, y, px) in albedo.enumerate_pixels() {
                let i = y as usize * step * w + x as usize * step;
                let rgb = result.albedo.each_ref().map(|p| p.data[i] as f64);
                let want = if result.status[i] == PixelStatus::Solved {
                    matrix.map(|row| {
                        let v = (row[0] * rgb[0] + row[1] * rgb[1] + row[2] * rgb[2]) as f32;
                        crate::maps::srgb::srgb8_direct(v.clamp(0.0, 1.0)) as u8
                    })
                } else {
                    [0; 3]
                };
                assert_eq!(px.0, want, "albedo at ({x}, {y}), step {step}");
            }
        }
    }

    /// The loupe's views at every pixel and at every 3rd pixel hold, pixel for pixel, what
    /// the page says they hold: the albedo's sRGB code by direct computation and the normal's
    /// `round((n * 0.5 + 0.5) * 255)`.
    #[test]
    fn full_views_hold_each_sampled_pixel_converted() {
        let (w, h) = (37, 11);
        let mut state = 7u32;
        let mut plane = |lo: f32, hi: f32| {
            let data = (0..w * h)
                .map(|_| {
                    state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    lo + (hi - lo) * (state >> 8) as f32 / (1u32 << 24) as f32
                })
                .collect();
            Plane::from_vec(w, h, data).unwrap()
        };
        let albedo = [plane(-0.1, 1.1), plane(0.0, 1.0), plane(0.0, 0.01)];
        let normal = [plane(-1.0, 1.0), plane(-1.0, 1.0), plane(0.0, 1.0)].map(Cow::Owned);
        let maps = FullMaps {
            width: w,
            height: h,
            albedo: Some(AlbedoMap::Planes(albedo.clone())),
            normal: Some(normal.clone()),
            confidence: None,
            missing: Vec::new(),
        };
        for step in [1, 3] {
            let (a, n) = full_views(&maps, step);
            let (a, n) = (a.unwrap(), n.unwrap());
            assert_eq!(
                a.dimensions(),
                (w.div_ceil(step) as u32, h.div_ceil(step) as u32)
            );
            for (x, y, px) in a.enumerate_pixels() {
                let i = y as usize * step * w + x as usize * step;
                let want = albedo
                    .each_ref()
                    .map(|p| crate::maps::srgb::srgb8_direct(p.data[i]) as u8);
                assert_eq!(px.0, want, "albedo at ({x}, {y}), step {step}");
                let want = normal
                    .each_ref()
                    .map(|p| ((p.data[i] * 0.5 + 0.5).clamp(0.0, 1.0) * 255.0).round() as u8);
                assert_eq!(
                    n.get_pixel(x, y).0,
                    want,
                    "normal at ({x}, {y}), step {step}"
                );
            }
        }
    }

    /// A weave-like test image: threads in two directions, colour steps between them, and
    /// pixel noise (what makes a JPEG large), over `h` rows.
    fn weave(w: u32, h: u32) -> RgbImage {
        let mut state = 12345u32;
        RgbImage::from_fn(w, h, |x, y| {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let noise = (state >> 27) as f32;
            let warp = ((x as f32 * 0.9).sin() * 0.5 + 0.5) * 120.0;
            let weft = ((y as f32 * 0.7).cos() * 0.5 + 0.5) * 90.0;
            let over = (x / 6 + y / 6) % 2 == 0;
            let base = if over { warp } else { weft };
            image::Rgb([
                (base + noise * 2.0) as u8,
                (base * 0.7 + 40.0 + noise) as u8,
                (base * 0.4 + 90.0 + noise * 1.5) as u8,
            ])
        })
    }

    #[test]
    fn the_sampled_size_predicts_the_whole_jpeg() {
        let sources = vec![("albedo", weave(900, 1100)), ("normal", weave(900, 1100))];
        let bands = band_ids(&sources);
        let sample = sample_bands(&bands, &sources);
        // Every eighth of the 35 bands of each view: 0, 8, 16, 24 and 32.
        assert_eq!(sample.len(), 2 * 5);
        for (quality, tables) in encodings() {
            let encoding = (quality, tables);
            let predicted = predicted_bytes(&sources, &encode_bands(&sources, &sample, encoding));
            let actual = base64_size(&encode_bands(&sources, &bands, encoding));
            let off = predicted as f64 / actual as f64 - 1.0;
            // The sample is an eighth of the bands of an image of uniform texture: its bytes
            // per row are the whole's up to the last band's short height and the texture's
            // row-to-row variation, well under the margin a skip needs.
            assert!(
                off.abs() < PREDICTION_MARGIN - 1.0,
                "q{quality} {tables:?}: predicted {predicted}, actual {actual}"
            );
        }
        // Too few bands to sample: encoded whole.
        let small = vec![("albedo", weave(64, 64))];
        assert!(sample_bands(&band_ids(&small), &small).is_empty());
    }

    /// Maps of a weave-like texture with noise, `w x h`, for the loupe's encodings.
    fn textured_maps(w: usize, h: usize) -> FullMaps<'static> {
        let mut state = 11u32;
        let mut noise = move || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        let mut plane = |f: &dyn Fn(f32, f32) -> f32, amount: f32| {
            let data = (0..w * h)
                .map(|i| f((i % w) as f32, (i / w) as f32) + amount * noise())
                .collect();
            Plane::from_vec(w, h, data).unwrap()
        };
        let threads = |x: f32, y: f32| 0.3 + 0.2 * (x * 0.7).sin() * (y * 0.4).cos();
        let albedo = [
            plane(&threads, 0.05),
            plane(&|x, y| 0.5 * threads(y, x), 0.05),
            plane(&|_, _| 0.1, 0.02),
        ];
        let normal = [
            plane(&|x, _| 0.4 * (x * 0.7).cos(), 0.05),
            plane(&|_, y| 0.4 * (y * 0.4).sin(), 0.05),
            plane(&|_, _| 0.8, 0.02),
        ]
        .map(Cow::Owned);
        FullMaps {
            width: w,
            height: h,
            albedo: Some(AlbedoMap::Planes(albedo)),
            normal: Some(normal),
            confidence: None,
            missing: Vec::new(),
        }
    }

    /// The loupe takes the standard Huffman tables where they fit the budget; where they miss
    /// it, optimised tables at the same quality for the largest bands, only as many as it
    /// takes (every band, where only all of them fit).
    #[test]
    fn optimised_tables_are_taken_only_where_the_standard_ones_miss_the_budget() {
        let maps = textured_maps(300, 1100);
        let (albedo, normal) = full_views(&maps, 1);
        let sources = vec![("albedo", albedo.unwrap()), ("normal", normal.unwrap())];
        let bands = band_ids(&sources);
        let encode = |tables| encode_bands(&sources, &bands, (88, tables));
        let (standard, optimised) = (
            encode(HuffmanTables::Standard),
            encode(HuffmanTables::Optimised),
        );
        let (standard_size, optimised_size) = (base64_size(&standard), base64_size(&optimised));
        assert!(
            optimised_size < standard_size,
            "{optimised_size} {standard_size}"
        );
        // Which table each band of a loupe took: `true` for optimised.
        let tables_of = |loupe: &Loupe| -> Vec<bool> {
            let bands = loupe.views.iter().zip(standard.iter().zip(&optimised));
            bands
                .map(|(band, ((_, s), (_, o)))| {
                    assert!(band.bytes == *s || band.bytes == *o, "one of the two JPEGs");
                    band.bytes == *o && band.bytes != *s
                })
                .collect()
        };
        let size_of =
            |loupe: &Loupe| -> usize { loupe.views.iter().map(|b| b.bytes.len() * 4 / 3).sum() };

        let roomy = loupe_views(&maps, standard_size);
        assert_eq!((roomy.step, roomy.quality), (1, 88));
        assert!(
            !tables_of(&roomy).contains(&true),
            "standard tables where they fit"
        );

        // Standard tables 2 % over the budget (within the sample's margin, so the whole is
        // encoded with them): some bands are re-encoded, not all.
        let budget = standard_size * 98 / 100;
        let near = loupe_views(&maps, budget);
        assert_eq!((near.step, near.quality), (1, 88));
        let tables = tables_of(&near);
        assert!(size_of(&near) <= budget);
        assert!(
            tables.contains(&true) && tables.contains(&false),
            "some of each: {tables:?}"
        );

        // Further over than the optimised tables save: all bands optimised.
        let budget = (standard_size + optimised_size) / 2;
        let tight = loupe_views(&maps, budget);
        assert_eq!((tight.step, tight.quality), (1, 88));
        assert!(size_of(&tight) <= budget);
        assert!(!tables_of(&tight).contains(&false), "all optimised");
    }

    #[test]
    fn the_bands_cover_each_view_once_in_order() {
        let sources = vec![("albedo", weave(40, 100)), ("normal", weave(40, 100))];
        let bands = encode_bands(&sources, &band_ids(&sources), (88, HuffmanTables::Standard));
        // 100 rows: bands from rows 0, 32, 64 and 96 (4 rows), albedo then normal.
        assert_eq!(bands.len(), 8);
        for (k, ((view, row), jpeg)) in bands.iter().enumerate() {
            assert_eq!((*view, *row), (k / 4, (k % 4) * LOUPE_BAND_ROWS));
            let decoded = image::load_from_memory(jpeg).unwrap().into_rgb8();
            let rows = if k % 4 == 3 {
                4
            } else {
                LOUPE_BAND_ROWS as u32
            };
            assert_eq!((decoded.width(), decoded.height()), (40, rows));
            // The band's own rows: its JPEG is near them, not near the view's top rows.
            let source = &sources[*view].1;
            let error = |from: u32| -> f64 {
                let mut sum = 0.0;
                for (x, y, px) in decoded.enumerate_pixels() {
                    let want = source.get_pixel(x, from + y);
                    sum += (0..3)
                        .map(|c| (px[c] as f64 - want[c] as f64).abs())
                        .sum::<f64>();
                }
                sum / (3 * decoded.width() * decoded.height()) as f64
            };
            if *row > 0 {
                assert!(error(*row as u32) < error(0), "band at row {row}");
            }
        }
    }
}
