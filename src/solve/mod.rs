//! Per-pixel photometric stereo (seed 004, eqs. 24-30): divide each measurement by the light's
//! intensity at that pixel, solve `L N = I'` by least squares for the scaled normal `N` in
//! four solves (R, G, B and luminance), normal = `N_lum / |N_lum|`, albedo from the colour
//! solves. Pure math on planes: no file I/O, no printing.
//!
//! A measurement is left out of a pixel's fit when it is not finite, saturated, or dark (at or
//! below `dark_threshold_sigma` times the sensor's noise floor, of the luminance or, where the
//! channels share one CFA sample, of that sample: a light in attached or cast shadow reads zero
//! whatever the normal, so it would only bias the fit). Pixels left with
//! fewer than three lights, or with lights too close to coplanar, are flagged, never NaN.

// The chain, each link importing only those above it: measurements and fits, the chi-square
// test, the sheen lobe, the robust fit, the exact kernel, the streaming kernel, the adaptive
// screen. `result` (the output planes), `lights`, `predict`, `options`, `lanes` and `tiles`
// are leaves they share.
mod adaptive;
mod chi_square;
pub mod consistency;
mod departures;
mod fast;
mod kernel;
mod lanes;
mod lights;
mod measure;
mod noise_sums;
mod options;
mod predict;
mod result;
mod robust;
mod sheen;
pub mod tiles;

use crate::error::{Error, Result};
use crate::plane::{FrameRelease, Frames, Mask};
use crate::progress::Progress;

pub use lights::{GainGrid, Illumination, LightModel, LightSource};
pub use options::{
    default_kernel_tolerance_deg, Estimator, KernelChoice, Method, Precision, RobustOptions,
    SolveOptions, Streaming, StreamingEstimator, TileTolerance, DEFAULT_TILE_TOLERANCE_DEG,
};
pub use predict::{elliptic_e, expected_angle_error, NoiseModel};
pub use result::SolveResult;
pub use sheen::SheenModel;

/// Rec. 709 luminance weights: the grayscale the normal is solved from (seed eq. 26).
pub const LUMINANCE_WEIGHTS: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// Which fit produced a pixel's solution (the confidence map's `fit` channel).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, Default)]
#[serde(rename_all = "snake_case")]
#[repr(u8)]
pub enum PixelFit {
    /// Not solved, or least squares over every usable light.
    #[default]
    LeastSquares = 0,
    /// Least squares after rejecting outlying lights (shadows, highlights).
    Robust = 1,
    /// The sheen model fitted with the normal (seed eqs. 21-23).
    Sheen = 2,
}

// SAFETY: a fieldless `repr(u8)` enum is one initialised byte, its number, with no padding:
// what bytemuck's `NoUninit` asks, so that a slice of fits can be read as their numbers in
// place (the report page reads a 16 MP solve's classes without a copy).
unsafe impl bytemuck::NoUninit for PixelFit {}

impl PixelFit {
    /// Every fit, in the order of their codes.
    pub const ALL: [PixelFit; 3] = [PixelFit::LeastSquares, PixelFit::Robust, PixelFit::Sheen];

    /// The fit's name in reports and JSON (`least_squares`, `robust`, `sheen`).
    pub fn name(self) -> &'static str {
        match self {
            PixelFit::LeastSquares => "least_squares",
            PixelFit::Robust => "robust",
            PixelFit::Sheen => "sheen",
        }
    }
}

/// What the solve needs besides the options.
pub struct SolveInput<'a> {
    /// The linear frames, one per light, in the order of the light source's lights.
    pub frames: &'a Frames,
    /// The lights: a rig (near or distant model) or bare distant directions.
    pub lights: LightSource<'a>,
    /// The sensor's noise, for dark thresholds, the model test and the predicted error.
    pub noise: NoiseModel,
    /// Exposure of these frames relative to the one the rig's LED powers were measured at.
    pub exposure: f64,
    /// Pixels to solve (`true`); everything else is left as `OutsideMask`.
    pub mask: Option<&'a Mask>,
}

/// Why a pixel has (or has not) a solution. Stored per pixel; `Solved` is the only state
/// whose normal and albedo mean anything.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
#[repr(u8)]
pub enum PixelStatus {
    /// A normal and albedo were solved from three or more usable lights.
    Solved = 0,
    /// Not part of the requested mask.
    OutsideMask = 1,
    /// Fewer than three lights left, mostly because they were dark.
    Dark = 2,
    /// Fewer than three lights left, mostly because they were saturated.
    Saturated = 3,
    /// Fewer than three lights left, mostly because the inputs were NaN or infinite.
    NonFinite = 4,
    /// The remaining lights are too close to coplanar to determine a normal.
    Degenerate = 5,
}

// SAFETY: as for `PixelFit` above: a fieldless `repr(u8)` enum, one initialised byte.
unsafe impl bytemuck::NoUninit for PixelStatus {}

impl PixelStatus {
    /// Every status, in the order of their codes.
    pub const ALL: [PixelStatus; 6] = [
        PixelStatus::Solved,
        PixelStatus::OutsideMask,
        PixelStatus::Dark,
        PixelStatus::Saturated,
        PixelStatus::NonFinite,
        PixelStatus::Degenerate,
    ];

    /// The status's name in reports and JSON (`solved`, `outside_mask`, `dark`, ...).
    pub fn name(self) -> &'static str {
        match self {
            PixelStatus::Solved => "solved",
            PixelStatus::OutsideMask => "outside_mask",
            PixelStatus::Dark => "dark",
            PixelStatus::Saturated => "saturated",
            PixelStatus::NonFinite => "non_finite",
            PixelStatus::Degenerate => "degenerate",
        }
    }
}

/// Solves every pixel of the frames. Rows are solved in parallel (rayon); `progress` sees one
/// step per row.
pub fn solve(
    input: &SolveInput,
    options: &SolveOptions,
    progress: &dyn Progress,
) -> Result<SolveResult> {
    solve_reusing(input, options, progress, None)
}

/// As [`solve`], writing into `previous`'s planes when they have the frames' size (a batch of
/// same-size captures passes each result on to the next solve once its maps are written):
/// fresh output memory costs the kernel a page fault and a zeroing pass per page, a sizeable
/// share of the streaming kernel's time (docs/solve.md). Same results as [`solve`].
pub fn solve_reusing(
    input: &SolveInput,
    options: &SolveOptions,
    progress: &dyn Progress,
    previous: Option<SolveResult>,
) -> Result<SolveResult> {
    solve_with(input, options, progress, previous, None)
}

/// As [`solve_reusing`], for a caller that drops the frames afterwards: `release`, made from
/// `input.frames`, gives their rows back to the kernel as the rows are solved
/// (see [`FrameRelease`]), so the outputs' pages reuse the frames' and the peak is lower. The
/// frames' rows may read as zeros afterwards. Same results as [`solve`].
///
/// It gives back at most what the outputs fault in while the solve runs: memory given back
/// beyond that is faulted in again by what runs after the solve (which would otherwise reuse
/// the frames' freed blocks). So nothing where the outputs reuse `previous`'s planes, and
/// nothing where a second pass may read the frames again (adaptive with a sheen model).
///
/// # Safety
/// No other thread reads `input.frames` while this runs: giving rows back writes zeros into
/// them (`release`'s pointers may write; made from `&mut` frames, it is the owner's consent).
/// Reading them afterwards is sound, and gives zeros where rows were given back.
pub unsafe fn solve_releasing(
    input: &SolveInput,
    options: &SolveOptions,
    progress: &dyn Progress,
    previous: Option<SolveResult>,
    release: &mut FrameRelease,
) -> Result<SolveResult> {
    let (width, height) = (input.frames.width, input.frames.height);
    let reused = previous.as_ref().is_some_and(|r| r.has_size(width, height));
    release.limit(if reused || may_solve_twice(options) {
        0
    } else {
        SolveResult::fresh_bytes_touched(
            width * height,
            options.predict_error,
            !options.streaming(),
        )
    });
    // With nothing to give back, the rows need not go in order.
    let release = (!release.is_empty()).then_some(release);
    solve_with(input, options, progress, previous, release)
}

fn solve_with(
    input: &SolveInput,
    options: &SolveOptions,
    progress: &dyn Progress,
    previous: Option<SolveResult>,
    release: Option<&mut FrameRelease>,
) -> Result<SolveResult> {
    let frames = input.frames;
    frames.validate()?;
    let (width, height) = (frames.width, frames.height);
    let illumination = Illumination::new(
        &input.lights,
        options.light_model,
        width,
        height,
        frames.window,
    )?;
    check_inputs(input, options, &illumination)?;
    let kernel = kernel::Kernel::new(input, options, &illumination);

    let previous = previous.filter(|r| r.has_size(width, height));
    progress.begin("solve", height as u64);
    let streaming = options.streaming();
    let reused = previous.is_some();
    let mut result = match previous {
        Some(mut r) => {
            if streaming {
                r.escalated = 0;
                r.sheen_everywhere = false;
            } else {
                r.reset();
            }
            r
        }
        // The streaming kernels write every output of every pixel, so lazily zeroed pages
        // need no prefill pass; the exact kernel relies on the unsolved defaults.
        None if streaming => SolveResult::zeroed(width, height),
        None => SolveResult::new(width, height),
    };
    result.escalated = match &options.kernel {
        KernelChoice::Streaming(streaming) => solve_streaming(
            input,
            streaming,
            &illumination,
            &kernel,
            &mut result,
            progress,
            reused,
            release,
        ),
        KernelChoice::Exact { .. } => solve_pass(
            input,
            &kernel,
            &illumination,
            &mut result,
            progress,
            false,
            release,
        ),
    };
    progress.end();
    if needs_sheen_everywhere(options, &result) {
        // The sheen lobe brightens many lights smoothly, and part of its bias on the normal is
        // indistinguishable from a Lambertian tilt at a single pixel: where the scene shows
        // sheen, every pixel gets the sheen fit.
        let kernel = kernel.forcing_sheen();
        progress.begin("sheen", height as u64);
        solve_pass(
            input,
            &kernel,
            &illumination,
            &mut result,
            progress,
            true,
            None,
        );
        result.sheen_everywhere = true;
        progress.end();
    }
    Ok(result)
}

/// Solves the pixels of the mask (only those a Lambertian fit solved, with `again`); returns how
/// many were escalated to the robust fit.
fn solve_pass(
    input: &SolveInput,
    kernel: &kernel::Kernel,
    illumination: &Illumination,
    result: &mut SolveResult,
    progress: &dyn Progress,
    again: bool,
    release: Option<&mut FrameRelease>,
) -> usize {
    let width = result.width;
    let escalated = std::sync::atomic::AtomicUsize::new(0);
    let rows = kernel::RowOut::split(result);
    let scratch = || kernel::Scratch::with_capacity(illumination.len());
    kernel::for_each_row(
        rows,
        input.frames,
        release,
        scratch,
        |scratch, y, mut row| {
            for x in 0..width {
                if input.mask.is_some_and(|m| !m.data[y * width + x]) {
                    continue;
                }
                if again && !row.is_lambertian(x) {
                    continue;
                }
                match illumination.point(x, y) {
                    Some(point) => kernel.solve_pixel(y * width + x, &point, scratch, &mut row, x),
                    None => row.status[x] = PixelStatus::Degenerate,
                }
            }
            escalated.fetch_add(row.escalated, std::sync::atomic::Ordering::Relaxed);
            progress.advance(1);
        },
    );
    escalated.into_inner()
}

/// Adaptive only: true when a sheen model is configured and more of the solved pixels needed
/// it in the first pass than `sheen_scene_fraction`.
fn needs_sheen_everywhere(options: &SolveOptions, result: &SolveResult) -> bool {
    if !may_solve_twice(options) {
        return false;
    }
    let solved = result.count(PixelStatus::Solved);
    solved > 0
        && result.count_fit(PixelFit::Sheen) as f64
            > options.robust.sheen_scene_fraction * solved as f64
}

/// Whether the first pass may call for a second over every pixel ([`needs_sheen_everywhere`]).
fn may_solve_twice(options: &SolveOptions) -> bool {
    options.estimator() == Estimator::Adaptive && options.robust.sheen.is_some()
}

/// The streaming kernel at the requested precision and coefficient source; for the adaptive
/// estimator followed, row by row, by the exact kernel where the screen asks for it. Returns
/// how many pixels the robust fit ran on.
#[allow(clippy::too_many_arguments)]
fn solve_streaming(
    input: &SolveInput,
    streaming: &Streaming,
    illumination: &Illumination,
    kernel: &kernel::Kernel,
    result: &mut SolveResult,
    progress: &dyn Progress,
    reused: bool,
    release: Option<&mut FrameRelease>,
) -> usize {
    let options = kernel.options();
    let (w, h) = (input.frames.width, input.frames.height);
    let planned = streaming
        .tiles
        .and_then(|t| tiles::plan(illumination, w, h, t.degrees()).map(|grid| (grid, t)));
    // The screen's slack for interpolated directions: the tolerance the tile planner kept the
    // grid within.
    let (coefficients, tile_error_deg) = match planned {
        Some((grid, t)) => (fast::Coefficients::Tiled(grid), t.degrees()),
        None => (fast::Coefficients::PerPixel, 0.0),
    };
    let mut ctx = fast::Context::new(input, options, illumination, &coefficients, kernel);
    ctx.reused_outputs = reused;
    ctx.set_tile_error(tile_error_deg);
    match (streaming.estimator, streaming.precision) {
        (StreamingEstimator::Adaptive, precision) => {
            let screen = adaptive::Screen::new(kernel.chi_square());
            match precision {
                Precision::F32 => adaptive::solve_streaming(
                    &ctx,
                    kernel,
                    &screen,
                    illumination,
                    result,
                    progress,
                    release,
                    fast::row_f32,
                ),
                Precision::F64 => adaptive::solve_streaming(
                    &ctx,
                    kernel,
                    &screen,
                    illumination,
                    result,
                    progress,
                    release,
                    fast::row_f64,
                ),
            }
        }
        (StreamingEstimator::LeastSquares, Precision::F32) => {
            fast::solve_rows::<f32>(&ctx, result, progress, release, fast::row_f32);
            0
        }
        (StreamingEstimator::LeastSquares, Precision::F64) => {
            fast::solve_rows::<f64>(&ctx, result, progress, release, fast::row_f64);
            0
        }
    }
}

/// Checks what the options cannot: that the frames, lights, mask and exposure agree, and the
/// thresholds' ranges. (The kernel choice holds only combinations the kernels run.)
fn check_inputs(input: &SolveInput, options: &SolveOptions, lights: &Illumination) -> Result<()> {
    let frames = input.frames.lights.len();
    if frames != lights.len() {
        return Err(Error::Invalid(format!(
            "the capture has {frames} light frames but there are {} lights",
            lights.len()
        )));
    }
    if frames > kernel::MAX_LIGHTS {
        return Err(Error::Invalid(format!(
            "{frames} lights: psscan solves at most {} per capture",
            kernel::MAX_LIGHTS
        )));
    }
    if let Some(mask) = input.mask {
        if mask.width != input.frames.width || mask.height != input.frames.height {
            return Err(Error::Invalid(format!(
                "mask is {}x{}, the capture is {}x{}",
                mask.width, mask.height, input.frames.width, input.frames.height
            )));
        }
    }
    if !(input.exposure.is_finite() && input.exposure > 0.0) {
        return Err(Error::Invalid(format!(
            "exposure scale must be positive, got {}",
            input.exposure
        )));
    }
    let condition_ok = options.max_condition > 1.0 && !options.max_condition.is_nan();
    let threshold_ok =
        options.dark_threshold_sigma >= 0.0 && options.dark_threshold_sigma.is_finite();
    if !condition_ok || !threshold_ok {
        return Err(Error::Invalid(
            "max_condition must exceed 1 and dark_threshold_sigma must be >= 0".into(),
        ));
    }
    options.robust.validate()
}

#[cfg(test)]
mod tests;

#[cfg(test)]
mod tests_fast;

#[cfg(test)]
mod tests_release;
