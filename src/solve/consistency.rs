//! Cross-frame consistency: is every frame of a set a photograph of the same surface?
//!
//! A frame that decoded to garbage whose values stay in range (a damaged compressed stream,
//! a camera fault) passes every per-frame check, yet it disagrees with what the other frames
//! say the surface is. On a subsample of pixels each frame is predicted from a Lambertian
//! least-squares fit of the *other* frames (a deleted residual, in units of its own noise
//! standard deviation), and each frame's residuals are summarised per block of the image by a
//! robust scale (1.4826 times the median absolute residual: the standard deviation of
//! Gaussian residuals, unmoved while under half of them are outliers). Blocks keep the check
//! local: damage past a byte of a lossless-JPEG tile spoils the rest of that tile.
//!
//! A block is judged only where the model explains the frames: where the median frame's
//! scale is within [`MODEL_GATE`] noise deviations. There a frame far beyond both the median
//! frame and its own noise is not a photograph of that surface. Where the surface departs from
//! the model (specular objects, cast shadows over most of a block: the DiLiGenT benchmark
//! objects depart by tens to thousands of deviations), a damaged frame cannot be told from a
//! highlight by this test, and the block is left to the solver's own model test.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::lights::{Illumination, LightModel, LightSource};
use super::predict::NoiseModel;
use super::LUMINANCE_WEIGHTS;
use crate::error::Result;
use crate::math::MAD_TO_SIGMA;
use crate::plane::{Frames, Mask};

/// About this many pixels are sampled, whatever the frames' size: the check costs the same
/// at 16 MP as at 0.1 MP (each block keeps about a thousand samples, so a block's MAD scale
/// has a relative standard error near 1.17 / sqrt(n) = 4 %).
const TARGET_SAMPLES: usize = 1 << 16;

/// The image is cut into `BLOCKS x BLOCKS` blocks, each judged on its own.
pub const BLOCKS: usize = 8;

/// A block needs at least this many samples in a frame to be judged there (a MAD scale from
/// 64 samples is good to about 15 %).
const MIN_BLOCK_SAMPLES: usize = 64;

/// A frame is refused where its robust residual scale in a block exceeds every bound below.
///
/// Against the other frames: in a judged block each frame's scale estimates the same spread,
/// the noise (the model holds there, see [`MODEL_GATE`]), to within the MAD's sampling error
/// (under 15 % at `MIN_BLOCK_SAMPLES`, 64). A frame whose damage covers over half of a block
/// has a median residual of the damage's own size; the damage also leaks into the other
/// frames' deleted fits, by the cross leverage `a_j' A^-1 a_k`, which with ten or more lights
/// is well under a third. So a damaged block stands at least three times the median frame's
/// scale, and a clean one within sampling error of it; four times leaves room for both.
pub const RATIO_BOUND: f64 = 4.0;

/// Against the noise model: a frame whose residuals are only noise has a scale of 1 (in its
/// own standard deviations); one that merely differs from very clean other frames by a
/// noise-sized amount is not refused. Damage in range is of the order of the signal, tens
/// to thousands of standard deviations.
pub const NOISE_BOUND: f64 = 5.0;

/// A block is judged when its median frame's scale is at most this many noise deviations:
/// the model then explains the frames to within the noise model's own uncertainty
/// (demosaicking, dark-frame subtraction and the sheen lobe make a correct model's residuals
/// up to about twice the nominal noise). Real non-Lambertian objects lie one to three orders
/// of magnitude above it.
pub const MODEL_GATE: f64 = 3.0;

/// A frame's figures from [`frame_consistency`].
#[derive(Clone, Debug, PartialEq)]
pub struct FrameFigures {
    /// The robust scale of the frame's deleted residuals over every sample, in noise
    /// standard deviations.
    pub scale: f64,
    /// Its largest ratio, over the judged blocks, of its scale to the median frame's there.
    pub worst_ratio: f64,
    /// The frame's scale (noise standard deviations) in that block.
    pub worst_scale: f64,
    /// That block, as `(column, row)` of the `BLOCKS x BLOCKS` grid.
    pub worst_block: (usize, usize),
}

impl FrameFigures {
    /// Whether the frame disagrees with the others beyond both bounds.
    pub fn inconsistent(&self) -> bool {
        self.worst_ratio > RATIO_BOUND && self.worst_scale > NOISE_BOUND
    }
}

/// The consistency of a set's frames.
#[derive(Clone, Debug, PartialEq)]
pub struct Consistency {
    /// Per frame, in frame order.
    pub frames: Vec<FrameFigures>,
    /// Pixels sampled.
    pub samples: usize,
    /// Blocks judged (where the model explains the frames, see [`MODEL_GATE`]), of
    /// `BLOCKS * BLOCKS`.
    pub judged_blocks: usize,
}

impl Consistency {
    /// The frames that disagree with the rest, in frame order.
    pub fn inconsistent(&self) -> Vec<usize> {
        (self.frames.iter().enumerate())
            .filter(|(_, f)| f.inconsistent())
            .map(|(k, _)| k)
            .collect()
    }
}

/// One sample's deleted residual in one frame: `(block, frame, |z|)`.
type Residual = (usize, usize, f32);

/// Measures how well each frame agrees with a Lambertian fit of the others (see the module
/// documentation), on about `TARGET_SAMPLES` (65 536) pixels inside `mask`, a regular
/// subsample. Sets with fewer than five lights are not judged (every frame's figures are
/// zero): the other frames' fit then has at most one degree of freedom to spare.
pub fn frame_consistency(
    frames: &Frames,
    lights: &LightSource,
    model: LightModel,
    noise: &NoiseModel,
    mask: Option<&Mask>,
) -> Result<Consistency> {
    let n = frames.lights.len();
    let (w, h) = (frames.width, frames.height);
    let ill = Illumination::new(lights, model, w, h, frames.window)?;
    let quiet = FrameFigures {
        scale: 0.0,
        worst_ratio: 0.0,
        worst_scale: 0.0,
        worst_block: (0, 0),
    };
    if n < 5 || ill.len() != n || w == 0 || h == 0 {
        return Ok(Consistency {
            frames: vec![quiet; n],
            samples: 0,
            judged_blocks: 0,
        });
    }
    let stride = (((w * h) as f64 / TARGET_SAMPLES as f64).sqrt().ceil() as usize).max(1);
    let rows: Vec<usize> = (stride / 2..h).step_by(stride).collect();
    let residuals: Vec<Residual> = rows
        .par_iter()
        .flat_map_iter(|&y| {
            let mut out = Vec::new();
            for x in (stride / 2..w).step_by(stride) {
                if mask.is_some_and(|m| !m.data[y * w + x]) {
                    continue;
                }
                let block = (y * BLOCKS / h) * BLOCKS + x * BLOCKS / w;
                pixel_residuals(frames, &ill, noise, x, y, |k, z| {
                    out.push((block, k, z.abs() as f32))
                });
            }
            out
        })
        .collect();
    let samples = rows.len() * (stride / 2..w).step_by(stride).len();
    let (frames, judged_blocks) = summarise(&residuals, n);
    Ok(Consistency {
        frames,
        samples,
        judged_blocks,
    })
}

/// Noise-floor deviations at or below which a reading is dark (shadowed): what the solve's
/// default takes.
const DARK_SIGMAS: f64 = 3.0;

/// The deleted residuals of pixel `(x, y)`: for each usable frame `k`, its luminance less the
/// Lambertian fit of the pixel's other usable frames, over the standard deviation of that
/// difference. A frame is usable where it is finite, not saturated and above the dark level
/// (three noise-floor deviations: shadowed readings say nothing of the normal).
///
/// A damaged frame would leak into every other frame's fit and lift their residuals too, so
/// the frame with the largest deleted residual at the pixel is also left out of the others'
/// fits (one step of a robust fit): its own residual stands, and the others are measured
/// against a fit it did not touch.
fn pixel_residuals(
    frames: &Frames,
    ill: &Illumination,
    noise: &NoiseModel,
    x: usize,
    y: usize,
    mut emit: impl FnMut(usize, f64),
) {
    let Some(point) = ill.point(x, y) else {
        return;
    };
    let i = y * frames.width + x;
    // The solve's own test of a dark light (on the pixel's CFA sample where its channels
    // share one), so that the frames judged here are the ones the solve uses.
    let dark = noise.dark_test(&LUMINANCE_WEIGHTS, DARK_SIGMAS);
    let mut rows: Vec<Row> = Vec::with_capacity(frames.lights.len());
    for (k, frame) in frames.lights.iter().enumerate() {
        if frame.saturated.as_ref().is_some_and(|m| m.data[i]) {
            continue;
        }
        let raw = frame.rgb_at(x, y).map(|v| v as f64);
        let inv = ill.rgb_scale(k).map(|s| 1.0 / s);
        let lum: f64 = (0..3).map(|c| LUMINANCE_WEIGHTS[c] * raw[c] * inv[c]).sum();
        let sample = ill.sample(k, &point);
        let var = noise.luminance_variance(&raw, &inv, &LUMINANCE_WEIGHTS, lum, (x, y));
        let usable = lum.is_finite() && !dark.is_dark(&raw, (x, y));
        if usable && sample.falloff > 0.0 && var > 0.0 {
            rows.push(Row {
                frame: k,
                light: sample.direction * sample.falloff,
                lum,
                var,
            });
        }
    }
    // Two rows left out of a fit of three unknowns still leave it one to spare.
    if rows.len() < 6 {
        return;
    }
    let mut normal = Matrix3::zeros();
    let mut rhs = Vector3::zeros();
    for row in &rows {
        normal += row.normal_term();
        rhs += row.rhs_term();
    }
    let first: Vec<Option<f64>> = rows
        .iter()
        .map(|row| row.deleted_residual(normal - row.normal_term(), rhs - row.rhs_term()))
        .collect();
    let Some(worst) = (0..rows.len())
        .filter(|&r| first[r].is_some())
        .max_by(|&a, &b| first[a].unwrap().abs().total_cmp(&first[b].unwrap().abs()))
    else {
        return;
    };
    let (normal, rhs) = (
        normal - rows[worst].normal_term(),
        rhs - rows[worst].rhs_term(),
    );
    for (r, row) in rows.iter().enumerate() {
        let z = if r == worst {
            first[r]
        } else {
            row.deleted_residual(normal - row.normal_term(), rhs - row.rhs_term())
        };
        if let Some(z) = z {
            emit(row.frame, z);
        }
    }
}

/// One usable reading of a pixel: its frame, the light's vector scaled by its falloff, the
/// luminance and its variance.
struct Row {
    frame: usize,
    light: Vector3<f64>,
    lum: f64,
    var: f64,
}

impl Row {
    fn normal_term(&self) -> Matrix3<f64> {
        self.light * self.light.transpose() / self.var
    }

    fn rhs_term(&self) -> Vector3<f64> {
        self.light * (self.lum / self.var)
    }

    /// This reading less the fit whose weighted normal equations are `normal b = rhs`, over
    /// the standard deviation of that difference; `None` when the fit is singular.
    fn deleted_residual(&self, normal: Matrix3<f64>, rhs: Vector3<f64>) -> Option<f64> {
        let inverse = normal.try_inverse()?;
        let predicted = self.light.dot(&(inverse * rhs)).max(0.0);
        let spread = self.var + self.light.dot(&(inverse * self.light));
        (spread.is_finite() && spread > 0.0).then(|| (self.lum - predicted) / spread.sqrt())
    }
}

/// Per frame: its overall robust scale and its worst judged block against the median frame
/// there; and how many blocks were judged.
fn summarise(residuals: &[Residual], n: usize) -> (Vec<FrameFigures>, usize) {
    let mut cells: Vec<Vec<f32>> = vec![Vec::new(); BLOCKS * BLOCKS * n];
    let mut whole: Vec<Vec<f32>> = vec![Vec::new(); n];
    for &(block, k, z) in residuals {
        cells[block * n + k].push(z);
        whole[k].push(z);
    }
    let scales: Vec<Option<f64>> = cells
        .iter_mut()
        .map(|c| (c.len() >= MIN_BLOCK_SAMPLES).then(|| mad_scale(c)))
        .collect();
    let mut frames: Vec<FrameFigures> = (whole.iter_mut())
        .map(|w| FrameFigures {
            scale: mad_scale(w),
            worst_ratio: 0.0,
            worst_scale: 0.0,
            worst_block: (0, 0),
        })
        .collect();
    let mut judged = 0;
    for block in 0..BLOCKS * BLOCKS {
        let cell = &scales[block * n..(block + 1) * n];
        let mut present: Vec<f64> = cell.iter().flatten().copied().collect();
        let median = median(&mut present);
        if !(median > 0.0 && median <= MODEL_GATE) {
            continue;
        }
        judged += 1;
        for (figures, own) in frames.iter_mut().zip(cell) {
            let Some(own) = *own else {
                continue;
            };
            let ratio = own / median;
            if ratio > figures.worst_ratio {
                figures.worst_ratio = ratio;
                figures.worst_scale = own;
                figures.worst_block = (block % BLOCKS, block / BLOCKS);
            }
        }
    }
    (frames, judged)
}

/// [`MAD_TO_SIGMA`] times the median of `abs_residuals` (already absolute): the standard
/// deviation of Gaussian residuals about zero, robust to under half of them being outliers.
fn mad_scale(abs_residuals: &mut [f32]) -> f64 {
    if abs_residuals.is_empty() {
        return 0.0;
    }
    let mid = abs_residuals.len() / 2;
    MAD_TO_SIGMA * *abs_residuals.select_nth_unstable_by(mid, f32::total_cmp).1 as f64
}

fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let mid = values.len() / 2;
    *values.select_nth_unstable_by(mid, f64::total_cmp).1
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plane::{LightFrame, RgbPlanes, SensorWindow};

    /// Ten distant lights around the vertical, a sphere-ish field of normals under them, and
    /// Gaussian-free frames rendered exactly (the noise model's floor sets the units).
    fn lambertian_set() -> (Frames, Vec<[f64; 3]>, Vec<[f64; 3]>, NoiseModel) {
        let (w, h) = (96, 80);
        let directions: Vec<[f64; 3]> = (0..10)
            .map(|k| {
                let azimuth = k as f64 * std::f64::consts::TAU / 10.0;
                let elevation: f64 = if k % 2 == 0 { 0.9 } else { 0.6 };
                [
                    elevation.cos() * azimuth.cos(),
                    elevation.cos() * azimuth.sin(),
                    elevation.sin(),
                ]
            })
            .collect();
        let intensities = vec![[1.0; 3]; 10];
        let noise = NoiseModel {
            photon: 0.0,
            floor: 1e-6,
            channel_scale: [1.0; 3],
            shared_cfa_sample: None,
        };
        // A deterministic pseudo-noise of one floor deviation keeps the scales near one.
        let mut state = 12345u64;
        let mut jitter = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 2.0 * 3f64.sqrt() * 1e-3
        };
        let lights = directions
            .iter()
            .map(|d| {
                let mut rgb = RgbPlanes::new(w, h);
                for y in 0..h {
                    for x in 0..w {
                        let (u, v) = (x as f64 / w as f64 - 0.5, y as f64 / h as f64 - 0.5);
                        let n = Vector3::new(0.6 * u, 0.6 * v, 1.0).normalize();
                        let albedo = [0.5, 0.4 + 0.2 * u.abs(), 0.3];
                        let shade = n.dot(&Vector3::from(*d)).max(0.0);
                        let j = jitter();
                        for (c, plane) in
                            [&mut rgb.r, &mut rgb.g, &mut rgb.b].into_iter().enumerate()
                        {
                            plane.data[y * w + x] = (albedo[c] * shade + j) as f32;
                        }
                    }
                }
                LightFrame {
                    rgb,
                    saturated: None,
                    cfa: None,
                    dn: None,
                    cfa_dn: None,
                }
            })
            .collect();
        let frames = Frames {
            width: w,
            height: h,
            window: SensorWindow::FULL,
            lights,
        };
        (frames, directions, intensities, noise)
    }

    fn check(frames: &Frames, d: &[[f64; 3]], i: &[[f64; 3]], noise: &NoiseModel) -> Consistency {
        let source = LightSource::Directions {
            directions: d,
            intensities: i,
        };
        frame_consistency(frames, &source, LightModel::Distant, noise, None).unwrap()
    }

    /// Where a pixel's channels share one CFA sample, a light whose sample is within three
    /// floor deviations is dark, as the solve takes it, however bright the pixel's luminance
    /// (its missing channels) is: the frame is not among the pixel's residuals.
    #[test]
    fn a_reading_dark_on_its_own_cfa_sample_is_left_out_as_the_solve_leaves_it() {
        let (mut frames, d, i, mut noise) = lambertian_set();
        noise.shared_cfa_sample = Some([[0, 1], [1, 2]]);
        let (x, y) = (40, 40); // an R site of RGGB
        let source = LightSource::Directions {
            directions: &d,
            intensities: &i,
        };
        let (w, h) = (frames.width, frames.height);
        let ill = Illumination::new(&source, LightModel::Distant, w, h, frames.window).unwrap();
        let used = |frames: &Frames| {
            let mut used = Vec::new();
            pixel_residuals(frames, &ill, &noise, x, y, |k, _| used.push(k));
            used
        };
        assert!(used(&frames).contains(&0), "{:?}", used(&frames));
        // Two floor deviations (the floor's deviation is 1e-3); G and B stay hundreds above.
        frames.lights[0].rgb.r.data[y * w + x] = 2e-3;
        let left = used(&frames);
        assert!(!left.contains(&0) && left.len() >= 6, "{left:?}");
    }

    #[test]
    fn clean_lambertian_frames_agree_and_their_residuals_are_noise_sized() {
        let (frames, d, i, noise) = lambertian_set();
        let c = check(&frames, &d, &i, &noise);
        assert!(c.inconsistent().is_empty(), "{c:?}");
        assert_eq!(c.judged_blocks, BLOCKS * BLOCKS);
        for f in &c.frames {
            // Uniform noise of one floor deviation (luminance deviation is the same, the
            // weights summing to one and the channels sharing the jitter): scale near one.
            assert!((0.5..2.0).contains(&f.scale), "{f:?}");
            assert!(f.worst_ratio < 2.0, "{f:?}");
        }
    }

    #[test]
    fn a_frame_with_a_band_of_in_range_garbage_is_named() {
        let (mut frames, d, i, noise) = lambertian_set();
        // The last third of frame 3's rows replaced by values wandering over the frame's own
        // range, as a damaged lossless-JPEG stream decodes after the damage.
        let (w, h) = (frames.width, frames.height);
        let mut state = 7u64;
        for y in 2 * h / 3..h {
            for x in 0..w {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
                let v = 0.05 + 0.5 * ((state >> 33) as f32 / (1u64 << 31) as f32);
                let rgb = &mut frames.lights[3].rgb;
                rgb.r.data[y * w + x] = v;
                rgb.g.data[y * w + x] = v;
                rgb.b.data[y * w + x] = 0.6 * v;
            }
        }
        let c = check(&frames, &d, &i, &noise);
        assert_eq!(c.inconsistent(), vec![3], "{c:?}");
        assert_eq!(c.frames[3].worst_block.1, BLOCKS - 1, "{c:?}");
    }

    #[test]
    fn frames_the_model_does_not_explain_are_not_judged() {
        let (mut frames, d, i, mut noise) = lambertian_set();
        // A noise model a hundred times too optimistic: every frame departs from the fit by
        // about a hundred deviations, as real specular objects do. Damage in frame 3 is then
        // not told from the surface's own departures, and no block is judged.
        noise.floor *= 1e-4;
        let w = frames.width;
        for v in &mut frames.lights[3].rgb.g.data[..w * 20] {
            *v *= 1.8;
        }
        let c = check(&frames, &d, &i, &noise);
        assert_eq!(c.judged_blocks, 0, "{c:?}");
        assert!(c.inconsistent().is_empty(), "{c:?}");
        assert!(c.frames.iter().all(|f| f.scale > 50.0), "{c:?}");
    }

    #[test]
    fn fewer_than_five_lights_are_not_judged() {
        let (mut frames, d, i, noise) = lambertian_set();
        frames.lights.truncate(4);
        let c = check(&frames, &d[..4], &i[..4], &noise);
        assert!(c.frames.iter().all(|f| f.worst_ratio == 0.0));
        assert_eq!(c.samples, 0);
    }
}
