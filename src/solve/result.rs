//! The solve's output planes ([`SolveResult`]): how they are allocated for each kernel,
//! reset for reuse, and counted.

use nalgebra::Vector3;

use super::{PixelFit, PixelStatus};
use crate::plane::Plane;

/// The solve's output, one value per pixel in planes of the frames' size. For pixels that are
/// not `Solved` the normal is (0, 0, 1), the albedo 0 and the error figures 0.
#[derive(Clone, Debug)]
pub struct SolveResult {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
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
    /// Lights in each pixel's final fit: the usable ones (not dark, saturated or non-finite),
    /// less any a robust fit rejected.
    pub lights_used: Vec<u8>,
    /// Why each pixel has or has not a solution.
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
    /// Whether these are `width x height` planes, which a solve of that size can write into.
    pub(super) fn has_size(&self, width: usize, height: usize) -> bool {
        (self.width, self.height) == (width, height)
    }

    /// Bytes of fresh output memory a solve into new planes first touches while it runs: the
    /// planes every kernel writes at every pixel (normal, albedo, residual, condition, lights
    /// used, status, and the predicted error where asked for), less what [`SolveResult::new`]'s
    /// prefill (for the exact kernel: `prefilled`) touches before it starts (the normal's z,
    /// the status). The `fit` plane, written only where a robust fit runs, is left out.
    pub(super) fn fresh_bytes_touched(
        pixels: usize,
        predicted_error: bool,
        prefilled: bool,
    ) -> usize {
        let planes = 8 + predicted_error as usize;
        let prefill = if prefilled { 4 + 1 } else { 0 };
        pixels * (4 * planes + 2 - prefill)
    }

    /// Outputs prefilled with the unsolved defaults (`OutsideMask`, normal (0, 0, 1)), for
    /// solvers that skip pixels.
    pub(crate) fn new(width: usize, height: usize) -> Self {
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
    pub(super) fn zeroed(width: usize, height: usize) -> Self {
        let n = width * height;
        let plane = || {
            let mut p = Plane::new(width, height, 0.0);
            crate::alloc::small_pages(&mut p.data);
            p
        };
        let mut lights_used = vec![0u8; n];
        crate::alloc::small_pages(&mut lights_used);
        let mut status = zeroed_u8_enum::<PixelStatus>(n);
        crate::alloc::small_pages(&mut status);
        let mut fit = zeroed_u8_enum::<PixelFit>(n);
        crate::alloc::small_pages(&mut fit);
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
            fit,
            escalated: 0,
            sheen_everywhere: false,
        }
    }

    /// Back to the state of [`SolveResult::new`], keeping the buffers.
    pub(super) fn reset(&mut self) {
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

    /// Pixels with `status`.
    pub fn count(&self, status: PixelStatus) -> usize {
        self.status.iter().filter(|&&s| s == status).count()
    }

    /// Pixels per status and solved pixels per fit (in the order of [`PixelStatus::ALL`] and
    /// [`PixelFit::ALL`]): [`Self::count`] and [`Self::count_fit`] of each, in one pass on
    /// every core (nine passes over 16 M pixels were most of the report's own time).
    pub fn class_counts(&self) -> ([usize; 6], [usize; 3]) {
        use rayon::prelude::*;
        const BLOCK: usize = 1 << 16;
        let add = |(mut s, mut f): ([usize; 6], [usize; 3]), (ds, df): ([usize; 6], [usize; 3])| {
            s.iter_mut().zip(ds).for_each(|(a, b)| *a += b);
            f.iter_mut().zip(df).for_each(|(a, b)| *a += b);
            (s, f)
        };
        let count_block = |(status, fit): (&[PixelStatus], &[PixelFit])| {
            let (mut s, mut f) = ([0usize; 6], [0usize; 3]);
            for (&status, &fit) in status.iter().zip(fit) {
                s[status as usize] += 1;
                f[fit as usize] += (status == PixelStatus::Solved) as usize;
            }
            (s, f)
        };
        (self.status.par_chunks(BLOCK))
            .zip(self.fit.par_chunks(BLOCK))
            .map(count_block)
            .reduce(|| ([0; 6], [0; 3]), add)
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
