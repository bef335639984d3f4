//! The material seen through the holes of a weave, and the colour it gives the pixels that
//! show it.
//!
//! A hole one or two pixels wide holds one CFA site of each channel at most, often none: its
//! missing channels were never sampled on its material, and interpolating along the pixel's
//! own material (see `hue`) can only take them from a thread beside it, which may be several
//! times brighter in them (a dark ground's green beside a green thread: three times). But the
//! holes of a textile on a table all show one material, the table, and over the whole image
//! its every channel is sampled many times: at the red sites of some holes, the green sites of
//! others. So the sites that no neighbour of their own colour continues (isolated: every
//! same-colour site two pixels away differs in reflectance or in normal by more than a
//! material's texture and noise) are gathered, and where those of each colour agree on one
//! reflectance (one material, not scattered glints or dust), each isolated site at that
//! reflectance takes that material's colour ratios.
//!
//! Where the holes show more than one material, or a scene has no holes, the isolated sites do
//! not agree and nothing changes.

use std::sync::Mutex;

use super::super::develop::median_and_sigma;
use super::rows::{interior_run, SplitRow};
use super::{continuity_change, CONTINUITY_SCALE};
use crate::plane::RgbPlanes;

/// The continuity change ([`continuity_change`]) above which no direction continues the pixel's
/// material: a direction there weighs under `e^-5` (0.7 %) of a perfect continuation.
const ISOLATED: f32 = 5.0 * CONTINUITY_SCALE * CONTINUITY_SCALE;

/// Isolated sites of each colour needed before their reflectances are read as one material.
const MIN_SITES: usize = 50;

/// Isolated sites past this share of an image's pixels are not holes in a weave but a
/// texture finer than the mosaic resolves, or noise: none is kept (each takes 16 bytes).
const MOST_SITES_PER_PIXEL: f64 = 0.25;

/// The isolated sites of an image, gathered band by band from parallel workers.
pub(super) struct IsolatedSites {
    sites: Mutex<Option<Vec<Isolated>>>,
    most: usize,
}

impl IsolatedSites {
    /// None yet, for an image of `pixels`.
    pub(super) fn new(pixels: usize) -> IsolatedSites {
        IsolatedSites {
            sites: Mutex::new(Some(Vec::new())),
            most: (pixels as f64 * MOST_SITES_PER_PIXEL) as usize,
        }
    }

    /// Moves a band's isolated sites in (`band` is left empty); past the most kept, drops
    /// them all for good.
    pub(super) fn add(&self, band: &mut Vec<Isolated>) {
        let mut sites = self.sites.lock().expect("not poisoned");
        if let Some(kept) = sites.as_mut() {
            if kept.len() + band.len() > self.most {
                *sites = None;
            } else {
                kept.append(band);
            }
        }
        band.clear();
    }

    /// The sites gathered: none where there were too many.
    pub(super) fn into_sites(self) -> Vec<Isolated> {
        let sites = self.sites.into_inner().expect("not poisoned");
        sites.unwrap_or_default()
    }
}

/// One isolated site: its pixel index and its log reflectance.
#[derive(Clone, Copy, Debug)]
pub(super) struct Isolated {
    pub index: usize,
    pub log: f32,
}

/// The interior pixels of one column parity in one row: `rows[2 + dy]` is row `y + dy` (of
/// width `w`) split by column parity, so that the same-colour sites two pixels away from split
/// index `j` are at `j - 1 ..= j + 1` of rows `y - 2`, `y` and `y + 2`.
pub(super) struct Run<'a> {
    pub w: usize,
    pub y: usize,
    pub parity: usize,
    pub rows: [&'a SplitRow; 5],
}

/// Pushes the isolated pixels of `run` onto `out`; `best` is scratch.
pub(super) fn isolated_of_run(run: &Run, best: &mut Vec<f32>, out: &mut Vec<Isolated>) {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked above).
        return unsafe { isolated_of_run_avx2(run, best, out) };
    }
    isolated_of_run_portable(run, best, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn isolated_of_run_avx2(run: &Run, best: &mut Vec<f32>, out: &mut Vec<Isolated>) {
    isolated_of_run_portable(run, best, out)
}

/// Every direction's change over the whole run, branch-free, kept as each pixel's smallest
/// (an early exit per pixel at the first continuing direction kept it scalar: three times
/// the cost of the ratios themselves).
#[inline(always)]
fn isolated_of_run_portable(
    &Run { w, y, parity, rows }: &Run,
    best: &mut Vec<f32>,
    out: &mut Vec<Isolated>,
) {
    let run = interior_run(w, parity);
    let len = run.len();
    if len == 0 {
        return;
    }
    best.clear();
    best.resize(len, f32::INFINITY);
    let best = &mut best[..len];
    let own_log = &rows[2].log[parity][run.clone()][..len];
    let own_n = rows[2].normal[parity]
        .each_ref()
        .map(|v| &v[run.clone()][..len]);
    for (r, dj) in DIRECTIONS {
        let start = run.start.wrapping_add_signed(dj);
        let log = &rows[r].log[parity][start..start + len];
        let n = rows[r].normal[parity]
            .each_ref()
            .map(|v| &v[start..start + len]);
        for k in 0..len {
            let cos = own_n[0][k] * n[0][k] + own_n[1][k] * n[1][k] + own_n[2][k] * n[2][k];
            best[k] = best[k].min(continuity_change(log[k] - own_log[k], cos));
        }
    }
    for (k, (&best, &log)) in best.iter().zip(own_log).enumerate() {
        // A black pixel (log -inf) has no colour to give.
        if best > ISOLATED && log.is_finite() {
            out.push(Isolated {
                index: y * w + parity + 2 * (run.start + k),
                log,
            });
        }
    }
}

/// The eight same-colour sites two pixels away: the split row (`2 + dy`, of the five) and the
/// split index's offset.
const DIRECTIONS: [(usize, isize); 8] = [
    (0, -1),
    (0, 0),
    (0, 1),
    (2, -1),
    (2, 1),
    (4, -1),
    (4, 0),
    (4, 1),
];

/// The material the isolated sites agree on (seen through the holes of a weave), and how many
/// pixels took its colour.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Backing {
    /// Its albedo in each channel: the median of the isolated sites of that channel.
    pub albedo: [f32; 3],
    /// Pixels that took its colour ratios.
    pub pixels: usize,
}

/// Finds the material the `isolated` sites agree on and gives its colour ratios to those of
/// them at its reflectance. `None` (and `ratios` unchanged) where some colour has too few
/// isolated sites or they spread over more than one material's texture and noise.
pub(super) fn colour_the_backing(
    pattern: [[u8; 2]; 2],
    isolated: &[Isolated],
    ratios: &mut RgbPlanes,
) -> Option<Backing> {
    let w = ratios.width();
    let colour_of = |i: usize| pattern[(i / w) % 2][(i % w) % 2] as usize;
    let mut by_colour: [Vec<f32>; 3] = Default::default();
    for site in isolated {
        by_colour[colour_of(site.index)].push(site.log);
    }
    let mut log = [0.0f32; 3];
    for (c, logs) in by_colour.iter().enumerate() {
        if logs.len() < MIN_SITES {
            return None;
        }
        let (centre, spread) = median_and_sigma(logs);
        if spread >= CONTINUITY_SCALE {
            return None;
        }
        log[c] = centre;
    }
    let mut pixels = 0;
    let RgbPlanes { r, g, b } = ratios;
    let mut planes = [&mut r.data, &mut g.data, &mut b.data];
    for site in isolated {
        let own = colour_of(site.index);
        if (site.log - log[own]).abs() >= CONTINUITY_SCALE {
            continue; // isolated, but not the backing (a glint, a fleck of another thread)
        }
        for (c, plane) in planes.iter_mut().enumerate() {
            plane[site.index] = (log[c] - log[own]).exp();
        }
        pixels += 1;
    }
    Some(Backing {
        albedo: log.map(f32::exp),
        pixels,
    })
}

#[cfg(test)]
mod tests {
    use super::super::ratios_along;
    use super::*;
    use crate::raw::shading::SiteFit;
    use crate::raw::Mosaic;
    use rand::{Rng, SeedableRng};

    const STRIPE: usize = 6;
    const THREADS: [[f32; 3]; 3] = [[0.42, 0.05, 0.05], [0.04, 0.16, 0.07], [0.035, 0.05, 0.17]];
    /// An olive table: not neutral, so that the test shows the colour is measured, not assumed;
    /// every channel a third or more off the threads', so that a hole's own sample tells it
    /// from them (where it does not, and the thread beside it is level like the table, the
    /// hole looks like the thread: see `hue`'s tests).
    const TABLE: [f32; 3] = [0.09, 0.09, 0.03];
    const NOISE: f32 = 0.01;

    /// Vertical threads `STRIPE` pixels wide, each a cylinder (its normal turning 70 degrees
    /// across it) with a fibre texture along it and 1 % sensor noise, and 1-pixel holes at the
    /// threads' edges, each showing `hole_colour(k)` (k counts the holes) lying flat. Returns
    /// the sites and which pixels are holes.
    fn weave(
        (w, h): (usize, usize),
        hole_colour: impl Fn(usize) -> [f32; 3],
    ) -> (Vec<SiteFit>, Vec<Option<[f32; 3]>>) {
        let pattern = Mosaic::parse_pattern("RGGB").unwrap();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(11);
        let mut holes = vec![None; w * h];
        let mut k = 0;
        for y in (3..h - 3).step_by(5) {
            for x in (STRIPE..w - 3).step_by(STRIPE) {
                // Alternately the last column of a thread and the first of the next, so that
                // the holes fall on every CFA colour.
                let x = x - (y / 5 + x / STRIPE) % 2;
                holes[y * w + x] = Some(hole_colour(k));
                k += 1;
            }
        }
        let sites = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let own = pattern[y % 2][x % 2] as usize;
                let noise = 1.0 + NOISE * 3f32.sqrt() * rng.gen_range(-1.0..1.0f32);
                let (colour, normal) = match holes[i] {
                    Some(colour) => (colour, [0.0, 0.0, 1.0]),
                    None => {
                        let across = (x % STRIPE) as f32 / (STRIPE - 1) as f32 - 0.5;
                        let tilt = across * 70f32.to_radians();
                        let fibre = 1.0 + 0.05 * (0.7 * y as f32).sin();
                        let colour = THREADS[(x / STRIPE) % 3].map(|c| c * fibre);
                        (colour, [tilt.sin(), 0.0, tilt.cos()])
                    }
                };
                SiteFit {
                    albedo: colour[own] * noise,
                    normal,
                }
            })
            .collect();
        (sites, holes)
    }

    #[test]
    fn holes_showing_one_table_take_its_colour_and_threads_keep_theirs() {
        let (w, h) = (192, 128);
        let pattern = Mosaic::parse_pattern("RGGB").unwrap();
        let (mut sites, holes) = weave((w, h), |_| TABLE);
        // White flecks (a stray fibre), isolated too but far brighter than the table: they
        // keep the colour the threads around give them.
        let flecks: Vec<usize> = (0..20).map(|k| (10 + 5 * k) * w + 20 + 7 * k).collect();
        for &i in &flecks {
            assert!(holes[i].is_none());
            sites[i] = SiteFit {
                albedo: 0.6,
                normal: [0.0, 0.0, 1.0],
            };
        }
        let (mut ratios, isolated) = ratios_along(w, h, pattern, sites.as_slice());
        assert!(flecks
            .iter()
            .all(|i| isolated.iter().any(|s| s.index == *i)));
        let before = ratios.clone();
        let backing = colour_the_backing(pattern, &isolated, &mut ratios).expect("a backing");
        // The median of each colour's hole sites: their noise is 1 %, so a few tenths of that.
        for c in 0..3 {
            let off = backing.albedo[c] / TABLE[c] - 1.0;
            assert!(off.abs() < NOISE, "channel {c}: {:?}", backing.albedo);
        }
        let n_holes = holes.iter().flatten().count();
        assert!(
            backing.pixels >= n_holes * 9 / 10 && backing.pixels <= n_holes,
            "{} of {n_holes} holes coloured",
            backing.pixels
        );
        let planes = [&ratios.r.data, &ratios.g.data, &ratios.b.data];
        let old = [&before.r.data, &before.g.data, &before.b.data];
        for i in 0..w * h {
            let own = pattern[(i / w) % 2][(i % w) % 2] as usize;
            let changed = (0..3).any(|c| planes[c][i] != old[c][i]);
            match holes[i] {
                // Two medians of 1 % noise each: the ratio is within 2 %.
                Some(table) if changed => {
                    for c in 0..3 {
                        let want = table[c] / table[own];
                        assert!((planes[c][i] / want - 1.0).abs() < 2.0 * NOISE, "pixel {i}");
                    }
                }
                Some(_) => {}
                None => assert!(!changed, "thread pixel {i} took the table's colour"),
            }
        }
    }

    #[test]
    fn holes_of_many_colours_are_left_as_they_were() {
        let (w, h) = (192, 128);
        let pattern = Mosaic::parse_pattern("RGGB").unwrap();
        // Each hole another material (a mixed ground, flecks of other threads): the isolated
        // sites spread over a factor of four in every channel.
        let (sites, _) = weave((w, h), |k| {
            let t = (k as f32 * 0.618).fract();
            [
                0.02 + 0.3 * t,
                0.3 - 0.25 * t,
                0.05 + 0.2 * (1.0 - 2.0 * t).abs(),
            ]
        });
        let (mut ratios, isolated) = ratios_along(w, h, pattern, sites.as_slice());
        let before = ratios.clone();
        assert_eq!(colour_the_backing(pattern, &isolated, &mut ratios), None);
        assert_eq!(ratios.r.data, before.r.data);
        assert_eq!(ratios.g.data, before.g.data);
        assert_eq!(ratios.b.data, before.b.data);
    }

    #[test]
    fn isolated_sites_past_a_quarter_of_the_pixels_are_dropped() {
        let site = |index| Isolated { index, log: 0.0 };
        let sites = IsolatedSites::new(100);
        sites.add(&mut (0..20).map(site).collect());
        let mut band: Vec<Isolated> = (20..25).map(site).collect();
        sites.add(&mut band);
        assert!(band.is_empty());
        assert_eq!(sites.into_sites().len(), 25);
        let sites = IsolatedSites::new(100);
        sites.add(&mut (0..20).map(site).collect());
        sites.add(&mut (20..26).map(site).collect());
        // Once over, later bands do not refill it.
        sites.add(&mut (30..31).map(site).collect());
        assert!(sites.into_sites().is_empty());
    }
}
