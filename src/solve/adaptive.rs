//! Adaptive escalation: least squares everywhere, the robust fit only where it is needed.
//!
//! A pixel escalates when its least-squares luminance residual is larger than the noise model
//! allows: the weighted sum of squared residuals `X = sum_k r_k^2 / s_k^2` of a Lambertian
//! pixel with independent Gaussian noise follows a chi-square distribution with `m - 3`
//! degrees of freedom (`m` lights used), and the test rejects at `significance_sigma` of
//! that distribution. The threshold therefore comes from the noise model, not from tuning: on
//! clean data a known small fraction escalates (0.13 % at 3 sigma), and escalating a clean
//! pixel is harmless because the robust fit keeps all lights that agree. Lights that were
//! dark or saturated are already out of the least-squares fit; a pixel with exactly three
//! lights left cannot be tested (any normal fits three lights) and stays least squares.

use std::sync::atomic::{AtomicUsize, Ordering};

use super::chi_square::ChiSquare;
use super::fast;
use super::kernel::{for_each_row, Kernel, RowOut, Scratch};
use super::lanes::Real;
use super::{PixelFit, PixelStatus, SolveResult};
use crate::plane::FrameRelease;
use crate::progress::Progress;

/// The streaming kernel's screen for the adaptive estimator: the exact kernel's chi-square
/// test on the fast least-squares fit.
///
/// The fast kernel weighs each light by its luminance variance under the noise model as the
/// exact kernel does and sums `sum_k r_k^2 / s_k^2` in the same pass (`fast::NoiseSums`), plus
/// a bound of how far its rounding and tiled light directions may put the sum below the exact
/// kernel's. A pixel passes where that is within the exact test's threshold (3 sigma of the
/// chi-square distribution with `m - 3` degrees of freedom): the exact kernel would pass it
/// too. Every other pixel the fast path solved goes to the exact kernel, whose own test
/// (exact variances, and the weighted fit where the least-squares one fails) decides whether
/// the robust fit runs. So the adaptive estimator escalates the same pixels on both kernels,
/// up to pixels within the slack of the threshold, which the exact kernel decides.
pub(super) struct Screen {
    /// The test's threshold per number of lights (index = lights, 0..=255; infinite up to
    /// three lights, which fit any normal).
    threshold: [f32; 256],
}

impl Screen {
    pub fn new(chi: &ChiSquare) -> Self {
        Screen {
            threshold: std::array::from_fn(|m| {
                if m <= 3 {
                    f32::INFINITY
                } else {
                    chi.threshold(m - 3) as f32
                }
            }),
        }
    }

    /// Collects in `failed` the columns of `row` that the fast kernel solved and whose
    /// `statistic` (see `fast::RowScratch::statistic`) the screen cannot pass.
    pub fn screen_row(&self, row: &RowOut, statistic: &[f32], failed: &mut Vec<usize>) {
        failed.clear();
        for (x, &tested) in statistic.iter().enumerate() {
            let fast = row.status[x] == PixelStatus::Solved && row.fit[x] == PixelFit::LeastSquares;
            // NaN fails too.
            let passes = tested <= self.threshold[row.lights[x] as usize];
            if fast && !passes {
                failed.push(x);
            }
        }
    }
}

/// The adaptive estimator on the streaming kernel: each row is solved by the fast least
/// squares (`row_fn`), then every pixel the [`Screen`] does not pass is solved again by the
/// exact kernel, which runs the exact chi-square test and, where that fails, the robust fit.
/// Returns how many pixels the robust fit ran on.
#[allow(clippy::too_many_arguments)]
pub(super) fn solve_streaming<T: Real>(
    ctx: &fast::Context,
    kernel: &Kernel,
    screen: &Screen,
    illumination: &super::Illumination,
    result: &mut SolveResult,
    progress: &dyn Progress,
    release: Option<&mut FrameRelease>,
    row_fn: fn(&fast::Context, usize, &mut RowOut, &mut fast::RowScratch<T>),
) -> usize {
    let width = result.width;
    let escalated = AtomicUsize::new(0);
    for_each_row(
        RowOut::split(result),
        ctx.frames,
        release,
        || {
            (
                fast::RowScratch::<T>::new(ctx),
                Scratch::with_capacity(illumination.len()),
                Vec::new(),
            )
        },
        |(fast_scratch, exact_scratch, failed), y, mut row| {
            row_fn(ctx, y, &mut row, fast_scratch);
            screen.screen_row(&row, fast_scratch.statistic(), failed);
            for &x in failed.iter() {
                row.reset(x, PixelStatus::OutsideMask);
                match illumination.point(x, y) {
                    Some(point) => {
                        kernel.solve_pixel(y * width + x, &point, exact_scratch, &mut row, x)
                    }
                    None => row.status[x] = PixelStatus::Degenerate,
                }
            }
            escalated.fetch_add(row.escalated, Ordering::Relaxed);
            progress.advance(1);
        },
    );
    escalated.into_inner()
}
