//! The streaming least-squares kernel: the same near-light solve as `kernel.rs`, restructured
//! for speed.
//!
//! - Three solves, not four: the luminance measurement is a fixed combination of R, G and B and
//!   a pixel's fit uses the same lights for every channel, so `N_lum = sum_c w_c N_c` exactly.
//! - No per-pixel light model evaluation: each light's direction and inverse falloff come from
//!   [`super::tiles`] (exact per pixel, or interpolated across tiles).
//! - Per pixel, the normal equations of the lights that pass the dark / saturated / finite
//!   tests (textiles shadow some light at a third of their pixels, so this is the common case,
//!   not a fallback), inverted in closed form, the residual from a second pass over the lights.
//! - Structure of arrays in chunks of [`LANES`] pixels of one row, in `f32` or `f64`, so LLVM
//!   vectorises the lanes (lights failing a test are blended out, not branched around);
//!   AVX-512 or AVX2 with FMA is chosen at run time, the baseline build stays portable. Rows run in
//!   parallel (rayon) and each reads each input plane once.
//!
//! - Where the solve predicts its error or screens its residual (the adaptive estimator), each
//!   light is weighed by its noise variance in the same pass ([`NoiseSums`]): the chi-square
//!   statistic the exact kernel tests and the predicted error come out of sums over the lights,
//!   so neither needs a second pass.
//!
//! Pixels left with fewer than three lights, degenerate or non-finite results, or in a tile
//! whose corners cannot be solved, are handed to the exact per-pixel kernel, which names the
//! reason. Fast-path pixels get normal, albedo, residual, condition number, lights used and,
//! where asked for, the predicted error.

use super::kernel::{for_each_row, Kernel, RowOut, Scratch};
use super::lanes::{
    adjugate, apply, dot, frob_sq, load_rgb, madd, mix, own_channels, prefetch, store, subtract_if,
    vectors, vectors6, Real, LANES, PREFETCH_AHEAD, V,
};
use super::lights::Illumination;
use super::noise_sums::{LightLanes, NoiseSums, Weighing};
use super::options::SolveOptions;
use super::predict::DarkTest;
use super::tiles::{self, exact_coefficients, Source, TileGrid};
use super::{PixelFit, PixelStatus, SolveInput, SolveResult, LUMINANCE_WEIGHTS};
use crate::plane::{FrameRelease, Frames};
use crate::progress::Progress;

/// Where the coefficients come from.
pub enum Coefficients {
    /// Computed exactly at every pixel.
    PerPixel,
    /// Interpolated across tiles.
    Tiled(TileGrid),
}

/// What the streaming kernel needs, shared by all rows.
pub struct Context<'a> {
    pub(super) frames: &'a Frames,
    illumination: &'a Illumination<'a>,
    coefficients: &'a Coefficients,
    exact: &'a Kernel<'a>,
    mask: Option<&'a crate::plane::Mask>,
    /// `s_ck`: exposure over the LED's colour scale, per light and channel.
    scale: Vec<[f64; 3]>,
    dark: DarkTest,
    max_condition: f64,
    normal_only: bool,
    /// The outputs hold a previous solve's values (`solve_reusing`): fast-path pixels must
    /// also write their fit, and their predicted error (0 where it is not computed), which
    /// fresh zeroed outputs already hold.
    pub reused_outputs: bool,
    /// Set where the lights are weighed by their noise: the adaptive screen's statistic or
    /// the predicted error is asked for.
    weighing: Option<Weighing>,
}

impl<'a> Context<'a> {
    pub fn new(
        input: &'a SolveInput,
        options: &SolveOptions,
        illumination: &'a Illumination<'a>,
        coefficients: &'a Coefficients,
        exact: &'a Kernel<'a>,
    ) -> Self {
        let inv_exposure = 1.0 / input.exposure;
        Context {
            frames: input.frames,
            illumination,
            coefficients,
            exact,
            mask: input.mask,
            scale: (0..illumination.len())
                .map(|k| illumination.rgb_scale(k).map(|s| inv_exposure / s))
                .collect(),
            dark: input
                .noise
                .dark_test(&LUMINANCE_WEIGHTS, options.dark_threshold_sigma),
            max_condition: options.max_condition,
            normal_only: options.normal_only,
            reused_outputs: false,
            weighing: Weighing::new(input, options),
        }
    }

    /// Sets how far tiled light directions may lie from the exact ones (degrees), the slack
    /// of the adaptive screen's statistic.
    pub fn set_tile_error(&mut self, degrees: f64) {
        if let Some(w) = &mut self.weighing {
            w.tile_rad = degrees.to_radians();
        }
    }
}

/// Per-thread buffers.
pub struct RowScratch<T> {
    /// Coefficients of the current chunk: `stride` rows of `LANES` values.
    coef: Vec<[T; LANES]>,
    /// Node coefficients interpolated to the current row, per node column, and their slope
    /// toward the next node column.
    row_left: Vec<T>,
    row_slope: Vec<T>,
    exact: Scratch,
    pixel: Vec<f64>,
    /// Per column of the row, the chi-square statistic of the fast path's fit plus its slack
    /// (0 where the exact kernel solved the pixel; see [`RowScratch::statistic`]).
    statistic: Vec<f32>,
}

impl<T: Real> RowScratch<T> {
    /// Buffers for the rows of `ctx`.
    pub fn new(ctx: &Context) -> Self {
        let stride = tiles::stride(ctx.illumination.len());
        let nodes_x = match ctx.coefficients {
            Coefficients::Tiled(g) => g.nodes_x,
            Coefficients::PerPixel => 0,
        };
        RowScratch {
            coef: vec![[T::zero(); LANES]; stride],
            row_left: vec![T::zero(); nodes_x * stride],
            row_slope: vec![T::zero(); nodes_x * stride],
            exact: Scratch::with_capacity(ctx.illumination.len()),
            pixel: vec![0.0; stride],
            statistic: vec![0.0; ctx.frames.width],
        }
    }

    /// Per column of the row last solved, the chi-square statistic `sum_k r_k^2 / s_k^2` of the
    /// fast least-squares fit plus a bound of how far the fast kernel's rounding and tiled
    /// light directions may put it below the exact kernel's (so a pixel whose value passes
    /// the test would pass the exact kernel's); 0 where the exact kernel solved the pixel
    /// (it tested it itself). Set only for the adaptive estimator.
    pub fn statistic(&self) -> &[f32] {
        &self.statistic
    }
}

/// Solves all rows with the streaming kernel in precision `T`.
pub fn solve_rows<T: Real>(
    ctx: &Context,
    result: &mut SolveResult,
    progress: &dyn Progress,
    release: Option<&mut FrameRelease>,
    row_fn: fn(&Context, usize, &mut RowOut, &mut RowScratch<T>),
) {
    for_each_row(
        RowOut::split(result),
        ctx.frames,
        release,
        || RowScratch::<T>::new(ctx),
        |scratch, y, mut row| {
            row_fn(ctx, y, &mut row, scratch);
            progress.advance(1);
        },
    );
}

/// The f32 kernel: AVX-512 or AVX2 with fused multiply-add where the CPU has them (checked
/// at run time, cached by std), the portable build otherwise.
pub fn row_f32(ctx: &Context, y: usize, row: &mut RowOut, scratch: &mut RowScratch<f32>) {
    #[cfg(target_arch = "x86_64")]
    {
        if simd::avx512() {
            // SAFETY: the CPU has the features `row_avx512` is compiled for.
            return unsafe { simd::row_avx512(ctx, y, row, scratch) };
        }
        if simd::avx2() {
            // SAFETY: as above.
            return unsafe { simd::row_avx2(ctx, y, row, scratch) };
        }
    }
    solve_row::<f32, false>(ctx, y, row, scratch)
}

/// The f64 kernel, dispatched as [`row_f32`].
pub fn row_f64(ctx: &Context, y: usize, row: &mut RowOut, scratch: &mut RowScratch<f64>) {
    #[cfg(target_arch = "x86_64")]
    {
        if simd::avx512() {
            // SAFETY: the CPU has the features `row_avx512` is compiled for.
            return unsafe { simd::row_avx512(ctx, y, row, scratch) };
        }
        if simd::avx2() {
            // SAFETY: as above.
            return unsafe { simd::row_avx2(ctx, y, row, scratch) };
        }
    }
    solve_row::<f64, false>(ctx, y, row, scratch)
}

/// The kernel compiled for wider vectors and fused multiply-add.
#[cfg(target_arch = "x86_64")]
mod simd {
    use super::{solve_row, Context, Real, RowOut, RowScratch};

    /// `PSSCAN_PORTABLE_KERNEL=1` forces the portable build (to compare, or to test it).
    fn allowed() -> bool {
        static PORTABLE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        !*PORTABLE.get_or_init(|| std::env::var_os("PSSCAN_PORTABLE_KERNEL").is_some())
    }

    pub fn avx512() -> bool {
        allowed()
            && is_x86_feature_detected!("avx512f")
            && is_x86_feature_detected!("avx512bw")
            && is_x86_feature_detected!("avx512vl")
            && avx2()
    }

    pub fn avx2() -> bool {
        allowed() && is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma")
    }

    #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2,fma")]
    pub unsafe fn row_avx512<T: Real>(
        ctx: &Context,
        y: usize,
        row: &mut RowOut,
        s: &mut RowScratch<T>,
    ) {
        solve_row::<T, true>(ctx, y, row, s)
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn row_avx2<T: Real>(
        ctx: &Context,
        y: usize,
        row: &mut RowOut,
        s: &mut RowScratch<T>,
    ) {
        solve_row::<T, true>(ctx, y, row, s)
    }
}

#[inline(always)]
fn solve_row<T: Real, const FMA: bool>(
    ctx: &Context,
    y: usize,
    row: &mut RowOut,
    scratch: &mut RowScratch<T>,
) {
    let w = ctx.frames.width;
    if w < LANES {
        for x in 0..w {
            exact_pixel(ctx, y, x, row, scratch);
        }
        scratch.statistic.fill(0.0);
        return;
    }
    if let Coefficients::Tiled(grid) = ctx.coefficients {
        grid.interpolate_row(
            y,
            (w, ctx.frames.height),
            &mut scratch.row_left,
            &mut scratch.row_slope,
        );
    }
    let mut x0 = 0;
    while x0 < w {
        // The last chunk is shifted left to stay whole; its overlap is solved twice, the same.
        let x = x0.min(w - LANES);
        x0 += LANES;
        let mut inside = [true; LANES];
        if let Some(mask) = ctx.mask {
            let m = &mask.data[y * w + x..y * w + x + LANES];
            inside.copy_from_slice(m);
            if !inside.iter().any(|&b| b) {
                // The outputs are not prefilled (`SolveResult::zeroed`).
                for l in 0..LANES {
                    row.reset(x + l, PixelStatus::OutsideMask);
                }
                scratch.statistic[x..x + LANES].fill(0.0);
                continue;
            }
        }
        prefetch(ctx.frames, y * w + x + PREFETCH_AHEAD);
        let (mut valid, linear) = fill_coefficients(ctx, x, y, scratch);
        for l in 0..LANES {
            valid[l] &= inside[l];
        }
        let stride = scratch.coef.len();
        let source = match linear {
            Some((jx, offset)) => Source::Linear {
                left: &scratch.row_left[jx * stride..(jx + 1) * stride],
                slope: &scratch.row_slope[jx * stride..(jx + 1) * stride],
                offset,
            },
            None => Source::Table(&scratch.coef),
        };
        let statistic = &mut scratch.statistic[x..x + LANES];
        let ok = solve_chunk::<T, FMA>(ctx, (x, y), &source, valid, row, statistic);
        // Without a prediction fast-path pixels have none: the plane is zero where this kernel
        // wrote it first, but the last chunk overlaps pixels the exact kernel may have solved.
        let predicted = ctx.weighing.is_some_and(|w| w.predict);
        if ctx.reused_outputs || x + LANES != x0 {
            if !predicted {
                row.predicted[x..x + LANES].fill(0.0);
            }
            row.fit[x..x + LANES].fill(PixelFit::LeastSquares);
        }
        for l in 0..LANES {
            if inside[l] && !ok[l] {
                exact_pixel(ctx, y, x + l, row, scratch);
                scratch.statistic[x + l] = 0.0;
            } else if !inside[l] {
                row.reset(x + l, PixelStatus::OutsideMask);
                scratch.statistic[x + l] = 0.0;
            }
        }
    }
}

/// Which lanes have coefficients, and for a chunk inside one tile the node column and the
/// lanes' offsets from it (no table is filled); otherwise the table in `s.coef` is filled.
#[inline(always)]
#[allow(clippy::type_complexity)]
fn fill_coefficients<T: Real>(
    ctx: &Context,
    x: usize,
    y: usize,
    s: &mut RowScratch<T>,
) -> ([bool; LANES], Option<(usize, [T; LANES])>) {
    let (w, h) = (ctx.frames.width, ctx.frames.height);
    let stride = s.coef.len();
    let mut valid = [false; LANES];
    match ctx.coefficients {
        Coefficients::Tiled(grid) => {
            let (jy, _) = grid.locate(y, h, grid.nodes_y);
            let (jx, _) = grid.locate(x, w, grid.nodes_x);
            let (jx_end, _) = grid.locate(x + LANES - 1, w, grid.nodes_x);
            if jx == jx_end {
                let x_node = T::of(grid.node_pos(jx, w) as f64);
                let mut offset = [T::zero(); LANES];
                for (l, o) in offset.iter_mut().enumerate() {
                    *o = T::of((x + l) as f64) - x_node;
                }
                return ([grid.tile_ok(jx, jy); LANES], Some((jx, offset)));
            }
            for (l, v) in valid.iter_mut().enumerate() {
                let (jx, _) = grid.locate(x + l, w, grid.nodes_x);
                let offset = T::of((x + l) as f64 - grid.node_pos(jx, w) as f64);
                for i in 0..stride {
                    let left = s.row_left[jx * stride + i];
                    s.coef[i][l] = left + s.row_slope[jx * stride + i] * offset;
                }
                *v = grid.tile_ok(jx, jy);
            }
        }
        Coefficients::PerPixel => {
            for (l, v) in valid.iter_mut().enumerate() {
                *v = exact_coefficients(ctx.illumination, (x + l) as f64, y as f64, &mut s.pixel);
                for i in 0..stride {
                    s.coef[i][l] = T::of(s.pixel[i]);
                }
            }
        }
    }
    (valid, None)
}

/// Solves `LANES` pixels starting at column `x` of `row` (frame row `y`); returns which lanes
/// succeeded. Every lane is written (and its `statistic` where the context computes it); the
/// caller overwrites the lanes that failed.
#[inline(always)]
fn solve_chunk<T: Real, const FMA: bool>(
    ctx: &Context,
    (x, y): (usize, usize),
    coef: &Source<T>,
    valid: [bool; LANES],
    row: &mut RowOut,
    statistic: &mut [f32],
) -> [bool; LANES] {
    let i0 = y * ctx.frames.width + x;
    let wt = [
        T::of(LUMINANCE_WEIGHTS[0]),
        T::of(LUMINANCE_WEIGHTS[1]),
        T::of(LUMINANCE_WEIGHTS[2]),
    ];
    let threshold = T::of(ctx.dark.luminance);
    let max = T::of(f32::MAX as f64);
    let zero = T::zero();
    let k_count = ctx.frames.lights.len();
    // Normal matrix (xx, xy, xz, yy, yz, zz) of all lights; dropped lights are subtracted.
    let mut a = [[zero; LANES]; 6];
    for (i, a) in a.iter_mut().enumerate() {
        *a = coef.get::<FMA>(4 * k_count + i);
    }
    // Right-hand sides: R, G, B, or the luminance alone in slot 0 for a normal-only solve;
    // and the sum of squared luminance measurements, for the residual.
    let mut b = [[[zero; LANES]; 3]; 3];
    let mut lum_sq = [zero; LANES];
    let mut dropped = [zero; LANES];
    let mut noise = ctx.weighing.map(|w| NoiseSums::<T>::new(w, (x, y)));
    // `DarkTest::is_dark` in lanes: the lanes' own CFA channel and its threshold, where the
    // channels share a sample.
    let dark_sample = ctx
        .dark
        .sample
        .map(|(pattern, threshold)| (own_channels(pattern, (x, y)), T::of(threshold)));
    for (k, frame) in ctx.frames.lights.iter().enumerate() {
        let [r, g, bl] = load_rgb::<T>(frame, i0, (x, y));
        const NONE_SATURATED: [bool; LANES] = [false; LANES];
        let sat: &[bool; LANES] = match &frame.saturated {
            Some(m) => m.data[i0..i0 + LANES].try_into().expect("a whole chunk"),
            None => &NONE_SATURATED,
        };
        let sk = &ctx.scale[k];
        let s = [T::of(sk[0]), T::of(sk[1]), T::of(sk[2])];
        let (lx, ly, lz) = (
            coef.get::<FMA>(3 * k),
            coef.get::<FMA>(3 * k + 1),
            coef.get::<FMA>(3 * k + 2),
        );
        let inv_falloff = coef.get::<FMA>(3 * k_count + k);
        let mut v = [[zero; LANES]; 3];
        let mut lum_k = [zero; LANES];
        let mut one = [zero; LANES];
        for l in 0..LANES {
            let lum = madd::<T, FMA>(wt[0], r[l], madd::<T, FMA>(wt[1], g[l], wt[2] * bl[l]));
            let bright = match &dark_sample {
                Some(([is_r, is_g, _], sample_threshold)) => {
                    // Selects, not an index per lane: they vectorise.
                    let own = if is_r[l] {
                        r[l]
                    } else if is_g[l] {
                        g[l]
                    } else {
                        bl[l]
                    };
                    own > *sample_threshold
                }
                None => lum > threshold,
            };
            let rgb = [r[l], g[l], bl[l]];
            let keep = !sat[l] && bright && lum <= max;
            let m = if keep { inv_falloff[l] } else { zero };
            for c in 0..3 {
                let value = if keep { rgb[c] } else { zero };
                v[c][l] = value * (s[c] * m);
            }
            lum_k[l] = madd::<T, FMA>(
                wt[0],
                v[0][l],
                madd::<T, FMA>(wt[1], v[1][l], wt[2] * v[2][l]),
            );
            lum_sq[l] = madd::<T, FMA>(lum_k[l], lum_k[l], lum_sq[l]);
            one[l] = if keep { zero } else { T::one() };
        }
        if let Some(noise) = &mut noise {
            let light = LightLanes {
                rgb: [&r, &g, &bl],
                scale: &s,
                inv_falloff: &inv_falloff,
                lum: &lum_k,
                dropped: &one,
                direction: [&lx, &ly, &lz],
            };
            noise.add::<FMA>(&light);
        }
        for l in 0..LANES {
            dropped[l] += one[l];
            // A select, not a multiply by 0 or 1: AVX-512 does it as a masked FMA.
            let drop = one[l] != zero;
            let (x, y, z) = (lx[l], ly[l], lz[l]);
            a[0][l] = subtract_if::<T, FMA>(drop, a[0][l], x, x);
            a[1][l] = subtract_if::<T, FMA>(drop, a[1][l], x, y);
            a[2][l] = subtract_if::<T, FMA>(drop, a[2][l], x, z);
            a[3][l] = subtract_if::<T, FMA>(drop, a[3][l], y, y);
            a[4][l] = subtract_if::<T, FMA>(drop, a[4][l], y, z);
            a[5][l] = subtract_if::<T, FMA>(drop, a[5][l], z, z);
        }
        if ctx.normal_only {
            for l in 0..LANES {
                b[0][0][l] = madd::<T, FMA>(lx[l], lum_k[l], b[0][0][l]);
                b[0][1][l] = madd::<T, FMA>(ly[l], lum_k[l], b[0][1][l]);
                b[0][2][l] = madd::<T, FMA>(lz[l], lum_k[l], b[0][2][l]);
            }
        } else {
            for c in 0..3 {
                for l in 0..LANES {
                    b[c][0][l] = madd::<T, FMA>(lx[l], v[c][l], b[c][0][l]);
                    b[c][1][l] = madd::<T, FMA>(ly[l], v[c][l], b[c][1][l]);
                    b[c][2][l] = madd::<T, FMA>(lz[l], v[c][l], b[c][2][l]);
                }
            }
        }
    }
    let used = V::splat(T::of(k_count as f64)) - V(dropped);
    let a = vectors6(&a);
    // The normal matrix's inverse is its adjugate over its determinant.
    let adj = adjugate(&a);
    let det = a[0] * adj[0] + a[1] * adj[1] + a[2] * adj[2];
    let inv_det = V::splat(T::one()) / det;
    let inv = [
        adj[0] * inv_det,
        adj[1] * inv_det,
        adj[2] * inv_det,
        adj[3] * inv_det,
        adj[4] * inv_det,
        adj[5] * inv_det,
    ];
    // Frobenius condition number of A, square-rooted to speak of L (as the exact kernel).
    let condition = (frob_sq(&a) * frob_sq(&inv)).sqrt().sqrt();
    let (n_lum, b_lum, n_rgb) = if ctx.normal_only {
        let b0 = vectors(&b[0]);
        (apply(&inv, &b0), b0, None)
    } else {
        let b = [vectors(&b[0]), vectors(&b[1]), vectors(&b[2])];
        let n_rgb = [apply(&inv, &b[0]), apply(&inv, &b[1]), apply(&inv, &b[2])];
        (
            [
                mix(&n_rgb, 0, &wt),
                mix(&n_rgb, 1, &wt),
                mix(&n_rgb, 2, &wt),
            ],
            [mix(&b, 0, &wt), mix(&b, 1, &wt), mix(&b, 2, &wt)],
            Some(n_rgb),
        )
    };
    // Residual of the luminance fit: for the least-squares solution `|r|^2 = |I|^2 - N . b`
    // (in f32 this loses digits when the residual is tiny against the signal; clamped at 0).
    let nb = n_lum[0] * b_lum[0] + n_lum[1] * b_lum[1] + n_lum[2] * b_lum[2];
    let residual = ((V(lum_sq) - nb).max(zero) / used).sqrt();
    let length = (n_lum[0] * n_lum[0] + n_lum[1] * n_lum[1] + n_lum[2] * n_lum[2]).sqrt();
    let inv_length = V::splat(T::one()) / length;
    let unit = [
        n_lum[0] * inv_length,
        n_lum[1] * inv_length,
        n_lum[2] * inv_length,
    ];
    let albedo = match &n_rgb {
        None => [length; 3],
        Some(n) => [dot(&n[0], &unit), dot(&n[1], &unit), dot(&n[2], &unit)],
    };
    let mut ok = valid;
    let (min_len, cond_max) = (T::of(1e-12), T::of(ctx.max_condition));
    let sum = albedo[0] + albedo[1] + albedo[2] + residual;
    // `&`, not `&&`: branch-free, so the lanes are tested in vectors.
    for l in 0..LANES {
        ok[l] &= (used.0[l] >= T::of(3.0))
            & (det.0[l] > zero)
            & (condition.0[l] <= cond_max)
            & (length.0[l] > min_len)
            & (length.0[l] <= max)
            & sum.0[l].is_finite();
    }
    for d in 0..3 {
        store(&mut row.normal[d][x..x + LANES], &unit[d]);
        store(&mut row.albedo[d][x..x + LANES], &albedo[d]);
    }
    store(&mut row.residual[x..x + LANES], &residual);
    store(&mut row.condition[x..x + LANES], &condition);
    if let Some(noise) = &noise {
        if noise.weighing.statistic {
            let tested = noise.statistic(&n_lum, &used, &length);
            store(statistic, &tested);
        }
        if noise.weighing.predict {
            let predicted = noise.predicted_deg(&inv, &n_lum, &length);
            store(&mut row.predicted[x..x + LANES], &predicted);
        }
    }
    for (o, u) in row.lights[x..x + LANES].iter_mut().zip(&used.0) {
        *o = u.to32() as u8;
    }
    row.status[x..x + LANES].fill(PixelStatus::Solved);
    ok
}

/// Solves one pixel with the exact kernel (dropping unusable lights).
fn exact_pixel<T>(ctx: &Context, y: usize, x: usize, row: &mut RowOut, s: &mut RowScratch<T>) {
    let w = ctx.frames.width;
    if ctx.mask.is_some_and(|m| !m.data[y * w + x]) {
        row.reset(x, PixelStatus::OutsideMask);
        return;
    }
    row.reset(x, PixelStatus::OutsideMask);
    match ctx.illumination.point(x, y) {
        Some(point) => ctx
            .exact
            .solve_pixel(y * w + x, &point, &mut s.exact, row, x),
        None => row.status[x] = PixelStatus::Degenerate,
    }
}
