//! What decides how a set is solved besides its data: the estimator, the kernel and method
//! ([`KernelChoice`], one value that cannot hold a combination the kernels cannot run), the
//! robust fit's tuning, and the thresholds. Plain values; the solve's links read them.

use serde::{Deserialize, Serialize};

use super::lights::LightModel;
use super::sheen::SheenModel;
use crate::error::{Conflict, Error, Result};

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
    /// Double precision.
    #[default]
    F64,
    /// Single precision: twice the lanes per vector, at a cost in accuracy that docs/bench
    /// records and `default_kernel_tolerance_deg` bounds.
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
    /// Every estimator: least squares, robust, adaptive.
    pub const ALL: [Estimator; 3] = [
        Estimator::LeastSquares,
        Estimator::Robust,
        Estimator::Adaptive,
    ];

    /// The estimator's name on the command line and in reports (`ls`, `robust`, `adaptive`).
    pub fn name(self) -> &'static str {
        match self {
            Estimator::LeastSquares => "ls",
            Estimator::Robust => "robust",
            Estimator::Adaptive => "adaptive",
        }
    }
}

/// The tile tolerance of the default kernel, degrees: light coefficients are shared across
/// tiles only where that moves no normal by more than this.
pub const DEFAULT_TILE_TOLERANCE_DEG: f64 = 0.01;

/// How far the default kernel's least-squares normal of a pixel may lie from the exact
/// kernel's, degrees, given the pixel's light-matrix `condition` number, for measurements the
/// Lambertian model fits (sensor noise adds its residual times the tiles' coefficient error,
/// of the order of the noise's own effect times the tile tolerance): twice the tile tolerance
/// (the tile planner aims at the tolerance on sampled test normals, it does not bound every
/// pixel: near the sensor's corners a pixel may move somewhat more) plus the forward error of
/// a single-precision least-squares solve, `condition^2 * K * eps` with K = 40 for the
/// ten-light normal equations (the bound `tests_fast` checks the f32 kernel against).
pub fn default_kernel_tolerance_deg(condition: f64) -> f64 {
    2.0 * DEFAULT_TILE_TOLERANCE_DEG
        + (condition * condition * 40.0 * f32::EPSILON as f64).to_degrees()
}

/// How far sharing light coefficients across tiles may move a normal, degrees: in (0, 1]
/// (checked where it is made, so a kernel choice never holds another value).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TileTolerance(f64);

impl TileTolerance {
    /// The default kernel's tolerance ([`DEFAULT_TILE_TOLERANCE_DEG`]).
    pub const DEFAULT: TileTolerance = TileTolerance(DEFAULT_TILE_TOLERANCE_DEG);

    /// `degrees`, when it lies in (0, 1].
    pub fn new(degrees: f64) -> Result<Self> {
        if degrees > 0.0 && degrees <= 1.0 {
            Ok(TileTolerance(degrees))
        } else {
            Err(Error::Invalid(format!(
                "tile tolerance must be in (0, 1] degrees, got {degrees}"
            )))
        }
    }

    /// The tolerance in degrees.
    pub fn degrees(self) -> f64 {
        self.0
    }
}

/// The estimators the streaming kernel runs (the robust one fits every pixel with the exact
/// kernel, so it has no streaming form).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StreamingEstimator {
    /// The fast least squares at every pixel.
    LeastSquares,
    /// The fast least squares at every pixel; the pixels whose residual the screen cannot
    /// pass are solved again by the exact kernel (and its robust fit where its test fails).
    Adaptive,
}

impl From<StreamingEstimator> for Estimator {
    fn from(estimator: StreamingEstimator) -> Self {
        match estimator {
            StreamingEstimator::LeastSquares => Estimator::LeastSquares,
            StreamingEstimator::Adaptive => Estimator::Adaptive,
        }
    }
}

/// The streaming kernel's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Streaming {
    /// The floating-point type the kernel computes in.
    pub precision: Precision,
    /// Share light coefficients across tiles (interpolated from their corners) within this
    /// tolerance; `None`: exact coefficients per pixel.
    pub tiles: Option<TileTolerance>,
    /// Least squares alone, or screened with the exact kernel behind it.
    pub estimator: StreamingEstimator,
}

/// Which kernel solves the pixels, with which estimator and method: one value, so that a
/// combination the kernels cannot run (the robust estimator or the SVD method on the
/// streaming kernel, a tile tolerance outside (0, 1]) cannot be built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum KernelChoice {
    /// The exact per-pixel kernel in f64: every estimator and method (the reference the
    /// streaming kernel is held to).
    Exact {
        /// How each pixel's least-squares problem is solved.
        method: Method,
        /// Which fit runs at each pixel: least squares, robust, or adaptive.
        estimator: Estimator,
    },
    /// The streaming kernel (`fast.rs`): least squares in chunks of pixels; see [`Streaming`].
    Streaming(Streaming),
}

impl Default for KernelChoice {
    /// The exact kernel with the normal equations and the default estimator.
    fn default() -> Self {
        KernelChoice::Exact {
            method: Method::NormalEquations,
            estimator: Estimator::default(),
        }
    }
}

impl KernelChoice {
    /// The exact kernel with the normal equations and `estimator`.
    pub fn exact(estimator: Estimator) -> Self {
        KernelChoice::Exact {
            method: Method::NormalEquations,
            estimator,
        }
    }

    /// The kernel that separate settings ask for: the streaming kernel where `streaming`,
    /// `precision` is `F32` or a tile tolerance is given, else the exact one. Refuses, naming
    /// the cause, the combinations the streaming kernel cannot run.
    pub fn new(
        estimator: Estimator,
        method: Method,
        precision: Precision,
        tile_tolerance_deg: Option<f64>,
        streaming: bool,
    ) -> Result<Self> {
        let tiles = tile_tolerance_deg.map(TileTolerance::new).transpose()?;
        if !(streaming || precision == Precision::F32 || tiles.is_some()) {
            return Ok(KernelChoice::Exact { method, estimator });
        }
        let estimator = match estimator {
            Estimator::LeastSquares => StreamingEstimator::LeastSquares,
            Estimator::Adaptive => StreamingEstimator::Adaptive,
            Estimator::Robust => return Err(Error::Incompatible(Conflict::RobustStreaming)),
        };
        if method == Method::Svd {
            return Err(Error::Incompatible(Conflict::SvdStreaming));
        }
        Ok(KernelChoice::Streaming(Streaming {
            precision,
            tiles,
            estimator,
        }))
    }

    /// The same kernel with another estimator; refused where the kernel cannot run it.
    pub fn with_estimator(self, estimator: Estimator) -> Result<Self> {
        match self {
            KernelChoice::Exact { method, .. } => Ok(KernelChoice::Exact { method, estimator }),
            KernelChoice::Streaming(s) => KernelChoice::new(
                estimator,
                Method::NormalEquations,
                s.precision,
                s.tiles.map(TileTolerance::degrees),
                true,
            ),
        }
    }

    /// The default kernel of `psscan solve` (and of `--precision f32`): the streaming f32 kernel with
    /// tiled coefficients ([`DEFAULT_TILE_TOLERANCE_DEG`]), whose normals lie within
    /// [`default_kernel_tolerance_deg`] of the exact kernel's, wherever the estimator and
    /// method allow it (the adaptive estimator sends the pixels its screen flags to the exact
    /// kernel). The robust estimator and the SVD method keep the exact kernel.
    pub fn fast_where_possible(self) -> Self {
        match self {
            KernelChoice::Exact {
                method: Method::NormalEquations,
                estimator: Estimator::LeastSquares,
            } => KernelChoice::fast(StreamingEstimator::LeastSquares),
            KernelChoice::Exact {
                method: Method::NormalEquations,
                estimator: Estimator::Adaptive,
            } => KernelChoice::fast(StreamingEstimator::Adaptive),
            other => other,
        }
    }

    /// The streaming f32 kernel with the default tile tolerance.
    pub fn fast(estimator: StreamingEstimator) -> Self {
        KernelChoice::Streaming(Streaming {
            precision: Precision::F32,
            tiles: Some(TileTolerance::DEFAULT),
            estimator,
        })
    }

    /// The estimator that decides each pixel's fit.
    pub fn estimator(&self) -> Estimator {
        match self {
            KernelChoice::Exact { estimator, .. } => *estimator,
            KernelChoice::Streaming(s) => s.estimator.into(),
        }
    }

    /// The least-squares method (the streaming kernel always uses the normal equations).
    pub fn method(&self) -> Method {
        match self {
            KernelChoice::Exact { method, .. } => *method,
            KernelChoice::Streaming(_) => Method::NormalEquations,
        }
    }

    /// The precision the pixels are solved in (the exact kernel's is f64).
    pub fn precision(&self) -> Precision {
        match self {
            KernelChoice::Exact { .. } => Precision::F64,
            KernelChoice::Streaming(s) => s.precision,
        }
    }

    /// The tile tolerance in degrees, where coefficients are shared across tiles.
    pub fn tile_tolerance_deg(&self) -> Option<f64> {
        match self {
            KernelChoice::Exact { .. } => None,
            KernelChoice::Streaming(s) => s.tiles.map(TileTolerance::degrees),
        }
    }

    /// Whether the streaming kernel solves the pixels.
    pub fn streaming(&self) -> bool {
        matches!(self, KernelChoice::Streaming(_))
    }
}

/// Everything that decides how a set is solved besides its data.
#[derive(Clone, Debug)]
pub struct SolveOptions {
    /// How the LEDs are modelled: near point sources, or distant lights (a rig's only; bare
    /// directions are distant).
    pub light_model: LightModel,
    /// The kernel, estimator and method (one value: see [`KernelChoice`]).
    pub kernel: KernelChoice,
    /// Tuning of the robust fit (used by `Estimator::Robust` and `Estimator::Adaptive`).
    pub robust: RobustOptions,
    /// A measurement whose luminance is at or below this many standard deviations of the
    /// sensor's noise floor counts as dark (shadowed) and is left out.
    pub dark_threshold_sigma: f64,
    /// Pixels whose light matrix has a condition number above this are flagged degenerate.
    pub max_condition: f64,
    /// Compute the per-pixel predicted error (a few more multiplies per light).
    pub predict_error: bool,
    /// Solve the luminance alone (one solve instead of three): the normal, and the luminance
    /// albedo in every albedo channel.
    pub normal_only: bool,
}

impl SolveOptions {
    /// The options with `estimator` on the exact kernel, everything else at its default.
    pub fn exact(estimator: Estimator) -> Self {
        SolveOptions {
            kernel: KernelChoice::exact(estimator),
            ..SolveOptions::default()
        }
    }

    /// These options with the default kernel of `psscan solve` (see
    /// [`KernelChoice::fast_where_possible`]).
    pub fn with_default_kernel(mut self) -> Self {
        self.kernel = self.kernel.fast_where_possible();
        self
    }

    /// The estimator that decides each pixel's fit.
    pub fn estimator(&self) -> Estimator {
        self.kernel.estimator()
    }

    /// Whether the streaming kernel solves the pixels (the least-squares and adaptive
    /// estimators; the adaptive one sends the pixels its screen flags to the exact kernel).
    pub fn streaming(&self) -> bool {
        self.kernel.streaming()
    }
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            light_model: LightModel::Near,
            kernel: KernelChoice::default(),
            robust: RobustOptions::default(),
            dark_threshold_sigma: 3.0,
            max_condition: 1e3,
            predict_error: true,
            normal_only: false,
        }
    }
}

/// The options as reports record them (`report.json`'s "options"): the kernel choice spelled
/// out as the separate settings the CLI's flags name, in the keys reports have always had.
#[derive(serde::Serialize)]
struct OptionsRecord<'a> {
    light_model: LightModel,
    method: Method,
    estimator: Estimator,
    robust: &'a RobustOptions,
    dark_threshold_sigma: f64,
    max_condition: f64,
    predict_error: bool,
    precision: Precision,
    tile_tolerance_deg: Option<f64>,
    normal_only: bool,
    /// The streaming kernel where neither the precision nor a tile tolerance says so.
    streaming_kernel: bool,
}

impl serde::Serialize for SolveOptions {
    fn serialize<S: serde::Serializer>(
        &self,
        serializer: S,
    ) -> std::result::Result<S::Ok, S::Error> {
        let k = &self.kernel;
        OptionsRecord {
            light_model: self.light_model,
            method: k.method(),
            estimator: k.estimator(),
            robust: &self.robust,
            dark_threshold_sigma: self.dark_threshold_sigma,
            max_condition: self.max_condition,
            predict_error: self.predict_error,
            precision: k.precision(),
            tile_tolerance_deg: k.tile_tolerance_deg(),
            normal_only: self.normal_only,
            streaming_kernel: k.streaming()
                && k.precision() == Precision::F64
                && k.tile_tolerance_deg().is_none(),
        }
        .serialize(serializer)
    }
}

/// Tuning of the robust fit and of the adaptive estimator's escalation test.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RobustOptions {
    /// The chi-square test of a fit against the noise model rejects at this many standard
    /// deviations (of the normal distribution, 3 = a false alarm on 0.13 % of clean pixels).
    pub significance_sigma: f64,
    /// A light whose studentised residual exceeds this many standard deviations is an outlier.
    pub outlier_sigma: f64,
    /// At most this fraction of a pixel's usable lights may be rejected as outliers either
    /// way (4 are always kept, so that the result can still be tested); the pass that rejects
    /// only darker lights (cast shadows) may go down to 4.
    pub max_rejected_fraction: f64,
    /// Model error of real surfaces, as a fraction of the signal, added in quadrature to the
    /// sensor noise in both tests (0: the noise model alone decides).
    pub relative_model_error: f64,
    /// The sheen lobe to fit with the normal where rejecting lights does not explain the data;
    /// `None`: no sheen fit.
    pub sheen: Option<SheenModel>,
    /// Adaptive estimator: when the sheen fit solved more than this fraction of the pixels in
    /// the first pass, the scene shows sheen and a second pass fits it at every pixel. 1 %
    /// is several times the chi-square test's false alarms on Lambertian scenes.
    pub sheen_scene_fraction: f64,
}

impl Default for RobustOptions {
    fn default() -> Self {
        RobustOptions {
            significance_sigma: 3.0,
            outlier_sigma: 4.0,
            max_rejected_fraction: 0.5,
            relative_model_error: 0.0,
            sheen: None,
            sheen_scene_fraction: 0.01,
        }
    }
}

impl RobustOptions {
    /// Rejects settings that have no meaning (a clear error rather than a silent default).
    pub fn validate(&self) -> Result<()> {
        let finite = |v: f64| v.is_finite();
        let sigmas_ok = finite(self.significance_sigma)
            && self.outlier_sigma > 0.0
            && finite(self.outlier_sigma);
        if !sigmas_ok {
            return Err(Error::Invalid(format!(
                "robust significance_sigma must be finite and outlier_sigma positive, got {} and {}",
                self.significance_sigma, self.outlier_sigma
            )));
        }
        if !(0.0..1.0).contains(&self.max_rejected_fraction) {
            return Err(Error::Invalid(format!(
                "robust max_rejected_fraction must be in [0, 1), got {}",
                self.max_rejected_fraction
            )));
        }
        if !(self.relative_model_error >= 0.0 && finite(self.relative_model_error)) {
            return Err(Error::Invalid(format!(
                "robust relative_model_error must be >= 0, got {}",
                self.relative_model_error
            )));
        }
        match &self.sheen {
            Some(sheen) => sheen.validate(),
            None => Ok(()),
        }
    }
}
