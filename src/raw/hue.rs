//! Colour ratios at every pixel from a mosaic of site reflectances (each CFA site's own
//! channel), interpolated along the directions in which the pixel's own material continues.
//!
//! A textile's colour changes in steps (thread to thread, thread to gap) a pixel or two wide,
//! and a missing channel taken from a neighbour across such a step is off by the whole step
//! (a dark channel next to a light thread: several times its value). So each neighbour of the
//! missing channel, at offset `d`, is weighted by how well the pixel's own channel continues
//! toward it: the own-channel site at `2d` (the same CFA site as the pixel) against the
//! pixel's own. Along a direction where it continues, the neighbour's ratio to the own channel
//! there (the mean of the two own-channel sites flanking it) is the pixel's ratio: the hue is
//! constant within a material even where its brightness (fibre ridges) is not. Where the far
//! flank is another material (a patch one or two pixels wide, such as a hole in the weave),
//! the own channel there is taken as the pixel's own.

mod backing;
mod rows;

pub use self::backing::Backing;
use self::backing::{colour_the_backing, isolated_of_run, Isolated, IsolatedSites, Run};
use self::rows::{Candidates, SplitRow};
use super::chroma::smooth_chroma;
use super::five_rows::FiveRows;
use super::mosaic::{mirror, GREEN};
use super::shading::{SiteFit, SiteRows};
use crate::math::exp_neg;
use crate::plane::RgbPlanes;

/// Relative change of the own channel (as a log ratio) at which a direction's weight falls
/// to `1/e` of the best direction's. Within one material the sites' reflectances differ by
/// their noise and the fibre texture (a few percent); across a thread or gap edge the colour
/// changes by tens of percent in most channels.
const CONTINUITY_SCALE: f32 = 0.1;

/// Log change of the own channel beyond which the far flank is taken for another material.
const FLANK_CONTINUES: f32 = 3.0 * CONTINUITY_SCALE;

/// Squared normal turn (radians^2) that counts like a squared log change of the own channel.
const NORMAL_WEIGHT: f32 = (CONTINUITY_SCALE / 0.2) * (CONTINUITY_SCALE / 0.2);

/// How far the site at log reflectance change `step` and normal turn `cos` (the cosine
/// between the two normals) is from continuing a pixel's material: the squared log change
/// plus the squared turn weighted by [`NORMAL_WEIGHT`]. Directions are weighed by it (here and
/// in `rows`), and a site none continues is isolated (`backing`).
#[inline(always)]
fn continuity_change(step: f32, cos: f32) -> f32 {
    let turn = (1.0 - cos.min(1.0)).max(0.0) * 2.0; // ~ angle^2
    step.powi(2) + turn * NORMAL_WEIGHT
}

/// Per pixel, each channel's ratio to the pixel's own channel (1 for the own channel), from
/// the sites' reflectances laid out as `pattern` (`sites`, read a row at a time),
/// then averaged over the pixels of the same chroma around (see [`smooth_chroma`]). A pixel
/// whose own reflectance is not positive gets ratios of 0 (it is black: its missing channels
/// are 0 too). The isolated pixels that show the material seen through the weave's holes take
/// its colour (see `backing`), which is returned where one was found.
pub fn colour_ratios(
    width: usize,
    height: usize,
    pattern: [[u8; 2]; 2],
    sites: &(impl SiteRows + ?Sized),
) -> (RgbPlanes, Option<Backing>) {
    let (mut out, isolated) = ratios_along(width, height, pattern, sites);
    let backing = colour_the_backing(pattern, &isolated, &mut out);
    smooth_chroma(pattern, &mut out);
    (out, backing)
}

/// Every pixel's ratios before the chroma average: [`ratios_at`] at every pixel, the interior
/// computed a row at a time (see `rows`); and the interior pixels that no neighbour of their
/// own colour continues.
fn ratios_along(
    width: usize,
    height: usize,
    pattern: [[u8; 2]; 2],
    sites: &(impl SiteRows + ?Sized),
) -> (RgbPlanes, Vec<Isolated>) {
    let (w, h) = (width, height);
    let mut out = RgbPlanes::new(w, h);
    let isolated = IsolatedSites::new(w * h);
    // Bands of rows: each fits the sites of its rows and the two either side of it as it
    // goes, and keeps the five rows around the one it works on (a pixel's neighbours are at
    // most two sites away, and stay within those when mirrored at the border), as they are
    // and split by column parity (see `rows`), moving them on one row at a time.
    out.par_bands_mut(BAND_ROWS, |y0, planes| {
        let mut kept = FiveRows::<KeptSites>::starting_at(y0.saturating_sub(2));
        let mut split = FiveRows::<SplitRow>::starting_at(y0.saturating_sub(2));
        let mut scratch = Default::default();
        let mut candidates = Candidates::default();
        let (mut band_isolated, mut best) = (Vec::new(), Vec::new());
        let [r, g, b] = planes;
        let band = r.chunks_mut(w).zip(g.chunks_mut(w)).zip(b.chunks_mut(w));
        for (y, ((r, g), b)) in (y0..).zip(band) {
            let mut planes = [r, g, b];
            kept.compute_to((y + 3).min(h), |k, row| {
                row.sites.resize(w, SiteFit::BLACK);
                sites.site_row(k, &mut row.sites, &mut scratch);
                row.logs.clear();
                row.logs.extend(row.sites.iter().map(|s| s.albedo.ln()));
            });
            let at = |x: isize, y: isize| {
                let (row, i) = (kept.row(mirror(y, h)), mirror(x, w));
                (&row.sites[i], row.logs[i])
            };
            if y < 2 || y + 2 >= h {
                for x in 0..w {
                    ratios_at(&at, pattern, (x, y), &mut planes);
                }
                continue;
            }
            split.compute_to(y + 3, |k, row| {
                row.fill(&kept.row(k).sites, &kept.row(k).logs)
            });
            let rows = std::array::from_fn(|k| split.row(y - 2 + k));
            for parity in 0..2 {
                let own = pattern[y % 2][parity];
                for c in (0..3).filter(|&c| c != own) {
                    let plane = &mut *planes[c as usize];
                    rows::ratios_of_run(pattern, y, parity, c, rows, &mut candidates, plane);
                }
                let run = Run { w, y, parity, rows };
                isolated_of_run(&run, &mut best, &mut band_isolated);
            }
            for x in 0..w {
                if x < 2 || x + 2 >= w {
                    ratios_at(&at, pattern, (x, y), &mut planes);
                } else {
                    planes[pattern[y % 2][x % 2] as usize][x] = 1.0;
                }
            }
        }
        isolated.add(&mut band_isolated);
    });
    (out, isolated.into_sites())
}

/// One row of sites as [`ratios_along`] keeps it: their fits, and each one's log reflectance,
/// taken once (the continuity test compares log ratios of sites, and taking the logarithm per
/// comparison cost most of that function's time).
#[derive(Default)]
struct KeptSites {
    sites: Vec<SiteFit>,
    logs: Vec<f32>,
}

/// Rows per band of [`colour_ratios`]'s parallel work: the four rows of sites around a band
/// are fitted and split once more than its own (a sixteenth more work at 64).
const BAND_ROWS: usize = 64;

/// Pixel `(x, y)`'s ratios into `planes` (its row of each), through `at` (mirrored at the
/// border): the reference that `rows` computes the interior by.
fn ratios_at<'a>(
    at: &impl Fn(isize, isize) -> (&'a SiteFit, f32),
    pattern: [[u8; 2]; 2],
    (x, y): (usize, usize),
    planes: &mut [&mut [f32]; 3],
) {
    let own = pattern[y % 2][x % 2] as usize;
    let own_site = at(x as isize, y as isize);
    for (c, plane) in planes.iter_mut().enumerate() {
        plane[x] = if c == own {
            1.0
        } else if own_site.0.albedo > 0.0 {
            let offsets = neighbours_of_channel(pattern, x, y, c as u8);
            ratio_along(at, (x as isize, y as isize), own_site, offsets)
        } else {
            0.0
        };
    }
}

/// Offsets of the nearest sites of `channel` around `(x, y)`: two (left/right or up/down) or
/// four (edges for G at an R or B site, diagonals for R at B and B at R).
fn neighbours_of_channel(
    pattern: [[u8; 2]; 2],
    x: usize,
    y: usize,
    channel: u8,
) -> &'static [(isize, isize)] {
    // Constant sets: this runs twice per pixel (tens of millions of times at 16 MP).
    const CROSS: [(isize, isize); 4] = [(-1, 0), (1, 0), (0, -1), (0, 1)];
    const ROW: [(isize, isize); 2] = [(-1, 0), (1, 0)];
    const COLUMN: [(isize, isize); 2] = [(0, -1), (0, 1)];
    const DIAGONALS: [(isize, isize); 4] = [(-1, -1), (1, -1), (-1, 1), (1, 1)];
    let (sy, sx) = (y % 2, x % 2);
    if pattern[sy][(sx + 1) % 2] == channel && pattern[(sy + 1) % 2][sx] == channel {
        &CROSS
    } else if pattern[sy][(sx + 1) % 2] == channel {
        &ROW
    } else if pattern[(sy + 1) % 2][sx] == channel {
        &COLUMN
    } else {
        debug_assert!(pattern[sy][sx] != GREEN);
        &DIAGONALS
    }
}

/// The ratio of the missing channel to the own one at `p`, from the neighbours at `offsets`.
/// `at` gives a site's fit and its log reflectance; `own` is `p`'s.
fn ratio_along<'a>(
    at: &impl Fn(isize, isize) -> (&'a SiteFit, f32),
    p: (isize, isize),
    (own, own_log): (&SiteFit, f32),
    offsets: &[(isize, isize)],
) -> f32 {
    let own_value = own.albedo;
    let mut candidates = [(0.0f32, 0.0f32); 4];
    let mut best = f32::INFINITY;
    for (slot, &(dx, dy)) in candidates.iter_mut().zip(offsets) {
        let (beyond, beyond_log) = at(p.0 + 2 * dx, p.1 + 2 * dy);
        let beyond = beyond.albedo;
        let (neighbour, _) = at(p.0 + dx, p.1 + dy);
        let change = if beyond > 0.0 {
            let n = neighbour.normal;
            let cos = own.normal[0] * n[0] + own.normal[1] * n[1] + own.normal[2] * n[2];
            continuity_change(beyond_log - own_log, cos)
        } else {
            f32::INFINITY
        };
        // The own channel at the neighbour: the mean of its two flanks where the material
        // continues to the far one; the pixel's own value where it does not (a one- or
        // two-pixel patch, whose far flank is another material).
        let flank = if (beyond_log - own_log).abs() < FLANK_CONTINUES {
            0.5 * (own_value + beyond)
        } else {
            own_value
        };
        *slot = (change, neighbour.albedo / flank);
        best = best.min(change);
    }
    let candidates = &candidates[..offsets.len()];
    if !best.is_finite() {
        // No direction continues (the pixel is an isolated bright site): plain mean.
        let sum: f32 = offsets
            .iter()
            .map(|&(dx, dy)| at(p.0 + dx, p.1 + dy).0.albedo)
            .sum();
        return sum / offsets.len() as f32 / own_value;
    }
    let (mut sum, mut weights) = (0.0f32, 0.0f32);
    for &(change, ratio) in candidates {
        // Beyond this excess over the best direction a weight is below e^-30: nothing.
        let excess = (change - best) / (CONTINUITY_SCALE * CONTINUITY_SCALE);
        if excess < 30.0 {
            let weight = exp_neg(excess);
            sum += weight * ratio;
            weights += weight;
        }
    }
    sum / weights
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raw::Mosaic;

    /// The fibre texture's brightness: 8 % either way, slow enough that linear interpolation
    /// over two sites misses it by at most 0.08 * (0.3 + 0.2)^2 / 2 = 1 % (second difference of
    /// the sine along an edge or diagonal step).
    fn shade(x: usize, y: usize) -> f32 {
        1.0 + 0.08 * (0.3 * x as f32 + 0.2 * y as f32).sin()
    }

    /// Two materials side by side, split by a vertical edge at column `edge`: each of
    /// constant hue and normal, brightness varying with [`shade`]. Returns the sites' fits
    /// and every pixel's true colour.
    fn two_materials(
        (w, h, edge): (usize, usize, usize),
        colours: [[f32; 3]; 2],
        normals: [[f32; 3]; 2],
    ) -> (Vec<SiteFit>, Vec<[f32; 3]>) {
        let pattern = Mosaic::parse_pattern("RGGB").unwrap();
        let mut sites = Vec::new();
        let mut truth = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let side = (x >= edge) as usize;
                let px = colours[side].map(|c| c * shade(x, y));
                sites.push(SiteFit {
                    albedo: px[pattern[y % 2][x % 2] as usize],
                    normal: normals[side],
                });
                truth.push(px);
            }
        }
        (sites, truth)
    }

    /// Worst relative ratio error away from the border.
    fn worst_ratio_error(
        size: (usize, usize, usize),
        sites: &[SiteFit],
        truth: &[[f32; 3]],
    ) -> f32 {
        let (w, h, _) = size;
        let pattern = Mosaic::parse_pattern("RGGB").unwrap();
        let (ratios, _) = colour_ratios(w, h, pattern, sites);
        let mut worst = 0.0f32;
        for y in 2..h - 2 {
            for x in 2..w - 2 {
                let i = y * w + x;
                let own = pattern[y % 2][x % 2] as usize;
                for c in 0..3 {
                    let want = truth[i][c] / truth[i][own];
                    worst = worst.max((ratios.channels()[c].data[i] / want - 1.0).abs());
                }
            }
        }
        worst
    }

    /// The bound: the fibre texture's 1 % interpolation error over the darkest shade (0.92);
    /// the other material's weight is below exp(-10) in both tests, its ratio at most 13 times.
    const BOUND: f32 = 0.01 / 0.92 + 6e-4;

    #[test]
    fn ratios_come_from_the_pixels_own_material_across_a_colour_edge() {
        let size = (24, 12, 11);
        let up = [0.0, 0.0, 1.0];
        // Every channel changes across the edge by at least ln(0.7 / 0.42) = 0.51.
        let colours = [[0.42, 0.05, 0.05], [0.7, 0.64, 0.46]];
        let (sites, truth) = two_materials(size, colours, [up, up]);
        let worst = worst_ratio_error(size, &sites, &truth);
        assert!(worst < BOUND, "worst relative ratio error {worst}");
        // A plain mean of the neighbours (bilinear) is off several times over at the edge.
        let (w, h, edge) = size;
        let pattern = Mosaic::parse_pattern("RGGB").unwrap();
        let values: Vec<f32> = sites.iter().map(|s| s.albedo).collect();
        let plain = super::super::mosaic::bilinear(w, h, pattern, &values);
        let i = 4 * w + edge - 1;
        let own = pattern[0][(edge - 1) % 2] as usize;
        let worst_plain = (0..3)
            .map(|c| {
                let got = plain.channels()[c].data[i] / plain.channels()[own].data[i];
                (got / (truth[i][c] / truth[i][own]) - 1.0).abs()
            })
            .fold(0.0f32, f32::max);
        assert!(worst_plain > 1.0, "bilinear at the edge: {worst_plain}");
    }

    /// A two-pixel hole in a green thread (a G site above a B site, the ground showing
    /// through, grey and level while the thread is tilted 20 degrees): the G pixel's blue is
    /// sampled only by the B pixel beside it, whose far flank is thread. Its ratio is that
    /// B sample over the pixel's own G, not over the mean of its G and the thread's.
    #[test]
    fn a_two_pixel_patch_takes_its_missing_channel_from_inside_the_patch() {
        let (w, h) = (24, 12);
        let pattern = Mosaic::parse_pattern("RGGB").unwrap();
        let tilt = 20f32.to_radians();
        let thread = ([0.04f32, 0.16, 0.07], [tilt.sin(), 0.0, tilt.cos()]);
        let ground = ([0.05f32, 0.05, 0.05], [0.0, 0.0, 1.0]);
        let hole = [(9, 4), (9, 5)];
        let sites: Vec<SiteFit> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let (colour, normal) = if hole.contains(&(x, y)) {
                    ground
                } else {
                    thread
                };
                SiteFit {
                    albedo: colour[pattern[y % 2][x % 2] as usize],
                    normal,
                }
            })
            .collect();
        let (ratios, _) = colour_ratios(w, h, pattern, sites.as_slice());
        let blue_over_green = ratios.channels()[2].data[4 * w + 9];
        // The thread's direction weighs exp(-2 (1 - cos 20 deg) NORMAL_WEIGHT / 0.1^2) =
        // exp(-3.0) = 0.049 of the hole's, with ratio 0.07 / 0.05: 1.9 % off; the chroma
        // average keeps to the hole's own two pixels.
        assert!(
            (blue_over_green - 1.0).abs() < 0.03,
            "blue / green in the hole: {blue_over_green} (true 1)"
        );
    }

    /// The row kernel is the per-pixel reference, bit for bit, on sites of every kind (black,
    /// isolated, continuing, tilted), at every CFA phase and at sizes where the interior is
    /// empty, one pixel or odd.
    #[test]
    fn rows_compute_what_the_reference_does_at_every_pixel() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
        for (w, h) in [(4, 4), (5, 5), (6, 7), (7, 6), (37, 70), (64, 33)] {
            for name in ["RGGB", "GBRG", "BGGR", "GRBG"] {
                let pattern = Mosaic::parse_pattern(name).unwrap();
                let sites: Vec<SiteFit> = (0..w * h)
                    .map(|_| {
                        // Albedos from two materials with noise, some black, normals tilted.
                        let albedo = match rng.gen_range(0..10) {
                            0 => 0.0,
                            1..=4 => 0.05 * rng.gen_range(0.9..1.1f32),
                            _ => 0.4 * rng.gen_range(0.9..1.1f32),
                        };
                        let tilt: f32 = rng.gen_range(0.0..0.7);
                        let turn: f32 = rng.gen_range(0.0..6.3);
                        let normal = [tilt.sin() * turn.cos(), tilt.sin() * turn.sin(), tilt.cos()];
                        SiteFit { albedo, normal }
                    })
                    .collect();
                let (got, _) = ratios_along(w, h, pattern, sites.as_slice());
                let logs: Vec<f32> = sites.iter().map(|s| s.albedo.ln()).collect();
                let at = |x: isize, y: isize| {
                    let i = mirror(y, h) * w + mirror(x, w);
                    (&sites[i], logs[i])
                };
                for y in 0..h {
                    let mut want = [vec![0.0f32; w], vec![0.0; w], vec![0.0; w]];
                    {
                        let [r, g, b] = &mut want;
                        let mut planes = [&mut r[..], &mut g[..], &mut b[..]];
                        for x in 0..w {
                            ratios_at(&at, pattern, (x, y), &mut planes);
                        }
                    }
                    for (c, want) in want.iter().enumerate() {
                        let row = &got.channels()[c].data[y * w..(y + 1) * w];
                        for x in 0..w {
                            assert_eq!(
                                row[x].to_bits(),
                                want[x].to_bits(),
                                "{name} {w}x{h}, pixel ({x}, {y}), channel {c}: {} vs {}",
                                row[x],
                                want[x]
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn the_normal_tells_materials_apart_where_the_own_channel_cannot() {
        // A red thread beside a grey gap: G and B are the same on both sides, so at a G or B
        // site only the normal (40 degrees apart: weight exp(-2 (1 - cos 40) / 0.2^2) =
        // exp(-11.7)) says which R neighbour is the pixel's own material.
        let size = (24, 12, 11);
        let tilted = [40f32.to_radians().sin(), 0.0, 40f32.to_radians().cos()];
        let colours = [[0.42, 0.05, 0.05], [0.05, 0.05, 0.05]];
        let (sites, truth) = two_materials(size, colours, [[0.0, 0.0, 1.0], tilted]);
        let worst = worst_ratio_error(size, &sites, &truth);
        assert!(worst < BOUND, "worst relative ratio error {worst}");
    }
}
