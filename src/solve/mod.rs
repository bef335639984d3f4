//! Per-pixel photometric stereo (seed 004, eqs. 24-30): divide each measurement by the light's
//! intensity at that pixel, solve `L N = I'` by least squares for the scaled normal `N` in
//! four solves (R, G, B and luminance), normal = `N_lum / |N_lum|`, albedo from the colour
//! solves. Pure math on planes: no file I/O, no printing.
//!
//! A measurement is left out of a pixel's fit when it is not finite, saturated, or dark (at or
//! below `dark_threshold_sigma` times the sensor's noise floor: a light in attached or cast
//! shadow reads zero whatever the normal, so it would only bias the fit). Pixels left with
//! fewer than three lights, or with lights too close to coplanar, are flagged, never NaN.

mod adaptive;
mod departures;
mod fast;
mod kernel;
mod lights;
mod predict;
mod robust;
mod sheen;
pub mod tiles;

use nalgebra::Vector3;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::plane::{Frames, Mask, Plane};
use crate::progress::Progress;

pub use lights::{GainGrid, Illumination, LightModel, LightSource};
pub use predict::{elliptic_e, expected_angle_error, NoiseModel};
pub use robust::RobustOptions;
pub use sheen::SheenModel;

/// Rec. 709 luminance weights: the grayscale the normal is solved from (seed eq. 26).
pub const LUMINANCE_WEIGHTS: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// How each pixel's least-squares problem is solved.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// The 3x3 normal equations `L^T L N = L^T I'`, inverted in closed form (f64). The fast
    /// path: one small matrix shared by the four solves.
    #[default]
    NormalEquations,
    /// The seed's method: singular value decomposition of `L` (nalgebra, f64). Slower; the
    /// reference the fast path is checked against.
    Svd,
}

/// The floating-point type of the streaming kernel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Precision {
    #[default]
    F64,
    /// Single precision: twice the lanes per vector; costs ~1e-4 degrees (see docs/bench).
    F32,
}

/// Which estimator solves each pixel.
#[derive(
    Clone,
    Copy,
    Debug,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    clap::ValueEnum,
    Default,
)]
pub enum Estimator {
    /// Plain least squares over every usable light (dark, saturated and non-finite
    /// measurements are always left out).
    #[serde(rename = "ls")]
    #[value(name = "ls")]
    LeastSquares,
    /// The robust fit (outlier rejection, then the sheen model where configured) at every
    /// pixel. See `robust`.
    #[serde(rename = "robust")]
    #[value(name = "robust")]
    Robust,
    /// Least squares everywhere; the robust fit only where the least-squares residual fails a
    /// chi-square test against the noise model. See `adaptive`. With the streaming kernel
    /// (`--precision f32`, `--tile-tolerance`) the fast least squares runs everywhere and
    /// only the pixels its residual screen flags are solved again by the exact kernel.
    #[default]
    #[serde(rename = "adaptive")]
    #[value(name = "adaptive")]
    Adaptive,
}

impl Estimator {
    pub const ALL: [Estimator; 3] = [
        Estimator::LeastSquares,
        Estimator::Robust,
        Estimator::Adaptive,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Estimator::LeastSquares => "ls",
            Estimator::Robust => "robust",
            Estimator::Adaptive => "adaptive",
        }
    }
}

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

impl PixelFit {
    pub const ALL: [PixelFit; 3] = [PixelFit::LeastSquares, PixelFit::Robust, PixelFit::Sheen];

    pub fn name(self) -> &'static str {
        match self {
            PixelFit::LeastSquares => "least_squares",
            PixelFit::Robust => "robust",
            PixelFit::Sheen => "sheen",
        }
    }
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct SolveOptions {
    pub light_model: LightModel,
    pub method: Method,
    pub estimator: Estimator,
    /// Tuning of the robust fit (used by `Estimator::Robust` and `Estimator::Adaptive`).
    pub robust: RobustOptions,
    /// A measurement whose luminance is at or below this many standard deviations of the
    /// sensor's noise floor counts as dark (shadowed) and is left out.
    pub dark_threshold_sigma: f64,
    /// Pixels whose light matrix has a condition number above this are flagged degenerate.
    pub max_condition: f64,
    /// Compute the per-pixel predicted error (a few more multiplies per light).
    pub predict_error: bool,
    /// Precision of the streaming kernel. `F32`, or a tile tolerance, selects the streaming
    /// kernel (`fast.rs`); `F64` without tiles keeps the exact per-pixel kernel.
    pub precision: Precision,
    /// Share light coefficients across tiles (interpolated from their corners) where that
    /// moves normals by at most this many degrees; `None`: exact coefficients per pixel.
    pub tile_tolerance_deg: Option<f64>,
    /// Solve the luminance alone (one solve instead of three): the normal, and the luminance
    /// albedo in every albedo channel.
    pub normal_only: bool,
    /// Use the streaming kernel even in f64 with per-pixel coefficients (F32 or a tile
    /// tolerance select it anyway).
    pub streaming_kernel: bool,
}

/// The tile tolerance of the default kernel, degrees: light coefficients are shared across
/// tiles only where that moves no normal by more than this.
pub const DEFAULT_TILE_TOLERANCE_DEG: f64 = 0.01;

/// How far the default kernel's least-squares normal of a pixel may lie from the exact
/// kernel's, degrees, given the pixel's light-matrix `condition` number, for measurements the
/// Lambertian model fits (sensor noise adds its residual times the tiles' coefficient error,
/// of the order of the noise's own effect times the tile tolerance): twice the tile tolerance
/// (the tile planner aims at the tolerance on sampled test normals, it does not bound every
/// pixel: near the sensor's corners pixels move up to ~1.2x it) plus the forward error of a single-precision least-squares solve, `condition^2 * K * eps`
/// with K = 40 for the ten-light normal equations (the bound `tests_fast` checks the f32
/// kernel against; about 5e-4 degrees at condition 10, mostly far less in practice).
pub fn default_kernel_tolerance_deg(condition: f64) -> f64 {
    2.0 * DEFAULT_TILE_TOLERANCE_DEG
        + (condition * condition * 40.0 * f32::EPSILON as f64).to_degrees()
}

impl SolveOptions {
    /// These options with the default kernel of `psscan solve`: the streaming f32 kernel with
    /// tiled coefficients ([`DEFAULT_TILE_TOLERANCE_DEG`]), whose normals lie within
    /// [`default_kernel_tolerance_deg`] of the exact kernel's, wherever the estimator and method
    /// allow it (the adaptive estimator sends the pixels its screen flags to the exact kernel).
    /// The robust estimator and the SVD method keep the exact kernel, which `--precision f64`
    /// also asks for.
    pub fn with_default_kernel(mut self) -> Self {
        if self.estimator != Estimator::Robust && self.method != Method::Svd {
            self.precision = Precision::F32;
            self.tile_tolerance_deg = Some(DEFAULT_TILE_TOLERANCE_DEG);
        }
        self
    }

    /// Whether the streaming kernel solves the pixels (the least-squares and adaptive
    /// estimators; the adaptive one sends the pixels its screen flags to the exact kernel).
    pub fn streaming(&self) -> bool {
        self.streaming_kernel
            || self.precision == Precision::F32
            || self.tile_tolerance_deg.is_some()
    }
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            light_model: LightModel::Near,
            method: Method::NormalEquations,
            estimator: Estimator::default(),
            robust: RobustOptions::default(),
            dark_threshold_sigma: 3.0,
            max_condition: 1e3,
            predict_error: true,
            precision: Precision::F64,
            tile_tolerance_deg: None,
            normal_only: false,
            streaming_kernel: false,
        }
    }
}

/// What the solve needs besides the options.
pub struct SolveInput<'a> {
    pub frames: &'a Frames,
    /// The lights: a rig (near or distant model) or bare distant directions.
    pub lights: LightSource<'a>,
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

impl PixelStatus {
    pub const ALL: [PixelStatus; 6] = [
        PixelStatus::Solved,
        PixelStatus::OutsideMask,
        PixelStatus::Dark,
        PixelStatus::Saturated,
        PixelStatus::NonFinite,
        PixelStatus::Degenerate,
    ];

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

/// The solve's output, one value per pixel in planes of the frames' size. For pixels that are
/// not `Solved` the normal is (0, 0, 1), the albedo 0 and the error figures 0.
#[derive(Clone, Debug)]
pub struct SolveResult {
    pub width: usize,
    pub height: usize,
    /// Unit normal in the world frame (x right, y toward the top of the image, z up).
    pub normal: [Plane; 3],
    /// Linear RGB albedo (the colour solves projected on the normal).
    pub albedo: [Plane; 3],
    /// RMS residual of the luminance fit over the lights used, in albedo units.
    pub residual: Plane,
    /// Predicted mean angular error from sensor noise (degrees); 0 when not computed.
    pub predicted_error_deg: Plane,
    /// Condition number (Frobenius estimate) of the pixel's light matrix.
    pub condition: Plane,
    pub lights_used: Vec<u8>,
    pub status: Vec<PixelStatus>,
    /// Which fit solved each pixel; `LeastSquares` where not solved.
    pub fit: Vec<PixelFit>,
    /// Pixels the robust fit ran on: for the adaptive estimator those whose least-squares fit
    /// failed the chi-square test (first pass), for the robust estimator all.
    pub escalated: usize,
    /// Adaptive estimator: the first pass found sheen, and a second pass fitted the sheen model
    /// at every pixel.
    pub sheen_everywhere: bool,
}

impl SolveResult {
    /// Outputs prefilled with the unsolved defaults (`OutsideMask`, normal (0, 0, 1)), for
    /// solvers that skip pixels.
    fn new(width: usize, height: usize) -> Self {
        let mut result = SolveResult::zeroed(width, height);
        result.normal[2].data.fill(1.0);
        result.status.fill(PixelStatus::OutsideMask);
        result
    }

    /// Outputs in zeroed memory, for a solver that writes every pixel's normal, albedo,
    /// residual, condition, lights used and status itself (the streaming kernel): a
    /// prefill would be a second pass over half a gigabyte at 16 MP. Fresh zeroed memory
    /// is mapped lazily, so the planes the solver leaves at zero (`predicted_error_deg`,
    /// `fit`) cost neither a write nor a page fault until they are read.
    fn zeroed(width: usize, height: usize) -> Self {
        let n = width * height;
        let plane = || {
            let mut p = Plane::new(width, height, 0.0);
            huge_pages(&mut p.data);
            p
        };
        let mut lights_used = vec![0u8; n];
        huge_pages(&mut lights_used);
        let mut status = zeroed_u8_enum::<PixelStatus>(n);
        huge_pages(&mut status);
        SolveResult {
            width,
            height,
            normal: [plane(), plane(), plane()],
            albedo: [plane(), plane(), plane()],
            residual: plane(),
            predicted_error_deg: plane(),
            condition: plane(),
            lights_used,
            status,
            fit: zeroed_u8_enum::<PixelFit>(n),
            escalated: 0,
            sheen_everywhere: false,
        }
    }

    /// Back to the state of [`SolveResult::new`], keeping the buffers.
    fn reset(&mut self) {
        for (d, p) in self.normal.iter_mut().enumerate() {
            p.data.fill(if d == 2 { 1.0 } else { 0.0 });
        }
        for p in self.albedo.iter_mut().chain([
            &mut self.residual,
            &mut self.predicted_error_deg,
            &mut self.condition,
        ]) {
            p.data.fill(0.0);
        }
        self.lights_used.fill(0);
        self.status.fill(PixelStatus::OutsideMask);
        self.fit.fill(PixelFit::LeastSquares);
        self.escalated = 0;
        self.sheen_everywhere = false;
    }

    /// Solved pixels per fit.
    pub fn count_fit(&self, fit: PixelFit) -> usize {
        self.status
            .iter()
            .zip(&self.fit)
            .filter(|(s, f)| **s == PixelStatus::Solved && **f == fit)
            .count()
    }

    pub fn count(&self, status: PixelStatus) -> usize {
        self.status.iter().filter(|&&s| s == status).count()
    }

    /// The unit normal at pixel index `i`.
    pub fn normal_at(&self, i: usize) -> Vector3<f64> {
        Vector3::new(
            self.normal[0].data[i] as f64,
            self.normal[1].data[i] as f64,
            self.normal[2].data[i] as f64,
        )
    }

    /// Mean of the predicted error over solved pixels (degrees).
    pub fn mean_predicted_error_deg(&self) -> f64 {
        let (sum, n) = self
            .status
            .iter()
            .zip(&self.predicted_error_deg.data)
            .filter(|(s, _)| **s == PixelStatus::Solved)
            .fold((0.0, 0usize), |(sum, n), (_, &e)| (sum + e as f64, n + 1));
        if n == 0 {
            0.0
        } else {
            sum / n as f64
        }
    }
}

/// A `u8`-sized enum whose zero byte is a valid value.
///
/// # Safety
/// Implementors are `#[repr(u8)]` and have a variant with discriminant 0.
unsafe trait ZeroIsValid: Copy {}

// SAFETY: `#[repr(u8)]`, `Solved = 0`.
unsafe impl ZeroIsValid for PixelStatus {}
// SAFETY: `#[repr(u8)]`, `LeastSquares = 0`.
unsafe impl ZeroIsValid for PixelFit {}

/// `n` copies of `T`'s zero value, in zeroed memory from the allocator (`calloc`: large
/// blocks are fresh pages, mapped on first touch), not written element by element.
fn zeroed_u8_enum<T: ZeroIsValid>(n: usize) -> Vec<T> {
    const { assert!(std::mem::size_of::<T>() == 1 && std::mem::align_of::<T>() == 1) };
    let mut bytes = std::mem::ManuallyDrop::new(vec![0u8; n]);
    // SAFETY: `T` has the size and alignment of `u8` (checked above), so the allocation's
    // layout is unchanged; every byte is 0, a valid `T` (`ZeroIsValid`); ownership moves
    // from `bytes`, which is never dropped.
    unsafe { Vec::from_raw_parts(bytes.as_mut_ptr() as *mut T, bytes.len(), bytes.capacity()) }
}

/// Advises the kernel to back `data` with transparent huge pages (Linux; a hint only).
fn huge_pages<T>(data: &mut [T]) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let start = data.as_mut_ptr() as usize;
        let end = start + std::mem::size_of_val(data);
        let (a, b) = (start.next_multiple_of(HUGE), end / HUGE * HUGE);
        if b > a {
            // SAFETY: the range lies inside `data`'s allocation; MADV_HUGEPAGE changes no
            // contents, only how the pages are backed.
            unsafe { libc::madvise(a as *mut libc::c_void, b - a, libc::MADV_HUGEPAGE) };
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = data;
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
/// fresh output memory costs the kernel a page fault and a zeroing pass per page, ~15% of
/// the streaming kernel's time at 16 MP. Same results as [`solve`].
pub fn solve_reusing(
    input: &SolveInput,
    options: &SolveOptions,
    progress: &dyn Progress,
    previous: Option<SolveResult>,
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

    let previous = previous.filter(|r| r.width == width && r.height == height);
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
    result.escalated = if streaming {
        solve_streaming(
            input,
            options,
            &illumination,
            &kernel,
            &mut result,
            progress,
            reused,
        )
    } else {
        solve_pass(input, &kernel, &illumination, &mut result, progress, false)
    };
    progress.end();
    if needs_sheen_everywhere(options, &result) {
        // The sheen lobe brightens many lights smoothly, and part of its bias on the normal is
        // indistinguishable from a Lambertian tilt at a single pixel: where the scene shows
        // sheen, every pixel gets the sheen fit.
        let kernel = kernel.forcing_sheen();
        progress.begin("sheen", height as u64);
        solve_pass(input, &kernel, &illumination, &mut result, progress, true);
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
) -> usize {
    let width = result.width;
    let escalated = std::sync::atomic::AtomicUsize::new(0);
    let rows = kernel::RowOut::split(result);
    rows.into_par_iter().enumerate().for_each(|(y, mut row)| {
        let mut scratch = kernel::Scratch::with_capacity(illumination.len());
        for x in 0..width {
            if input.mask.is_some_and(|m| !m.data[y * width + x]) {
                continue;
            }
            if again && !row.is_lambertian(x) {
                continue;
            }
            match illumination.point(x, y) {
                Some(point) => kernel.solve_pixel(y * width + x, &point, &mut scratch, &mut row, x),
                None => row.status[x] = PixelStatus::Degenerate,
            }
        }
        escalated.fetch_add(row.escalated, std::sync::atomic::Ordering::Relaxed);
        progress.advance(1);
    });
    escalated.into_inner()
}

/// Adaptive only: true when a sheen model is configured and more of the solved pixels needed
/// it in the first pass than `sheen_scene_fraction`.
fn needs_sheen_everywhere(options: &SolveOptions, result: &SolveResult) -> bool {
    if options.estimator != Estimator::Adaptive || options.robust.sheen.is_none() {
        return false;
    }
    let solved = result.count(PixelStatus::Solved);
    solved > 0
        && result.count_fit(PixelFit::Sheen) as f64
            > options.robust.sheen_scene_fraction * solved as f64
}

/// The streaming kernel at the requested precision and coefficient source; for the adaptive
/// estimator followed, row by row, by the exact kernel where the screen asks for it. Returns
/// how many pixels the robust fit ran on.
fn solve_streaming(
    input: &SolveInput,
    options: &SolveOptions,
    illumination: &Illumination,
    kernel: &kernel::Kernel,
    result: &mut SolveResult,
    progress: &dyn Progress,
    reused: bool,
) -> usize {
    let (w, h) = (input.frames.width, input.frames.height);
    let coefficients = match options.tile_tolerance_deg {
        Some(tolerance) => match tiles::plan(illumination, w, h, tolerance) {
            Some(grid) => fast::Coefficients::Tiled(grid),
            None => fast::Coefficients::PerPixel,
        },
        None => fast::Coefficients::PerPixel,
    };
    let mut ctx = fast::Context::new(input, options, illumination, &coefficients, kernel);
    ctx.reused_outputs = reused;
    if options.estimator == Estimator::Adaptive {
        // The screen's slack for interpolated directions: the tolerance the tile planner kept
        // the grid within.
        let tile_error_deg = match &coefficients {
            fast::Coefficients::Tiled(_) => options.tile_tolerance_deg.unwrap_or(0.0),
            fast::Coefficients::PerPixel => 0.0,
        };
        let chi = kernel.chi_square();
        let screen = adaptive::Screen::new(chi, options, input, illumination, tile_error_deg);
        let (kernel, screen) = (kernel, &screen);
        return match options.precision {
            Precision::F32 => adaptive::solve_streaming(
                &ctx,
                kernel,
                screen,
                illumination,
                result,
                progress,
                fast::row_f32,
            ),
            Precision::F64 => adaptive::solve_streaming(
                &ctx,
                kernel,
                screen,
                illumination,
                result,
                progress,
                fast::row_f64,
            ),
        };
    }
    match options.precision {
        Precision::F32 => fast::solve_rows::<f32>(&ctx, result, progress, fast::row_f32),
        Precision::F64 => fast::solve_rows::<f64>(&ctx, result, progress, fast::row_f64),
    }
    0
}

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
    if let Some(t) = options.tile_tolerance_deg {
        if !(t > 0.0 && t <= 1.0) {
            return Err(Error::Invalid(format!(
                "tile tolerance must be in (0, 1] degrees, got {t}"
            )));
        }
    }
    if options.streaming() && options.estimator == Estimator::Robust {
        return Err(Error::Invalid(
            "the robust estimator fits every pixel with the exact kernel: drop --precision f32 \
             and --tile-tolerance, or use --estimator adaptive (the streaming least squares, \
             the robust fit only where the residual asks for it)"
                .into(),
        ));
    }
    if options.streaming() && options.method == Method::Svd {
        return Err(Error::Invalid(
            "the SVD method is per pixel in f64 only: drop --precision f32 and --tile-tolerance"
                .into(),
        ));
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
