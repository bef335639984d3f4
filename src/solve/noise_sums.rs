//! The noise weighing of the streaming kernel (`fast.rs`): each light weighed by its
//! luminance variance under the noise model in the same pass as the fit, so the chi-square
//! statistic the adaptive screen tests and the predicted error come out of sums over the
//! lights without a second pass.

use super::lanes::{
    adjugate, apply, dot, madd, own_channel, sandwich, vectors6, Real, LANES, SYM, V,
};
use super::options::SolveOptions;
use super::{SolveInput, LUMINANCE_WEIGHTS};

/// What weighing each light by its noise needs: the noise model and what the weights are for.
#[derive(Clone, Copy)]
pub(super) struct Weighing {
    pub(super) noise: super::NoiseModel,
    /// The chi-square test's relative model error, squared.
    pub(super) relative_var: f64,
    /// Compute the chi-square statistic of the least-squares fit (the adaptive screen).
    pub(super) statistic: bool,
    /// Compute the predicted error.
    pub(super) predict: bool,
    /// How far the tiled light directions may lie from the exact ones (radians; 0 for exact
    /// coefficients): the statistic's slack.
    pub(super) tile_rad: f64,
}

impl Weighing {
    /// The weighing `options` ask for (`None`: neither the statistic nor the prediction).
    pub(super) fn new(input: &SolveInput, options: &SolveOptions) -> Option<Self> {
        let statistic = options.streaming() && options.estimator() == super::Estimator::Adaptive;
        let predict = options.predict_error;
        (statistic || predict).then_some(Weighing {
            noise: input.noise,
            relative_var: options.robust.relative_model_error.powi(2),
            statistic,
            predict,
            tile_rad: 0.0,
        })
    }
}

/// One light's values in a chunk, as [`NoiseSums::add`] reads them.
pub(super) struct LightLanes<'a, T> {
    /// The raw channel values.
    pub(super) rgb: [&'a [T; LANES]; 3],
    /// Exposure over the LED's colour scale, per channel.
    pub(super) scale: &'a [T; 3],
    pub(super) inv_falloff: &'a [T; LANES],
    /// The light-normalised luminance (0 where the light is dropped).
    pub(super) lum: &'a [T; LANES],
    /// 1 where the light is dropped (dark, saturated, not finite), else 0.
    pub(super) dropped: &'a [T; LANES],
    pub(super) direction: [&'a [T; LANES]; 3],
}

/// Sums over a chunk's lights, each weighed by its luminance variance `s_k^2` under the noise
/// model (`NoiseModel::luminance_variance`, the exact kernel's), from which the chi-square
/// statistic of the least-squares fit and its predicted error follow without a second pass:
///
/// - `sum_k r_k^2 / t_k^2 = Q0 - 2 N . q + N^T P N` with `t_k^2` the test variance (`s_k^2`
///   plus the model error and storage precision, as `ChiSquare::prepare`), `Q0 = sum w I^2`,
///   `q = sum w I l`, `P = sum w l l^T`, `w = 1 / t^2`;
/// - the normal's covariance `A^-1 (sum_k s_k^2 l_k l_k^T) A^-1` (`predict`).
pub(super) struct NoiseSums<T> {
    pub(super) weighing: Weighing,
    /// Per lane, which channel holds the pixel's own CFA sample (shared-sample frames).
    own: Option<[u8; LANES]>,
    q0: [T; LANES],
    q: [[T; LANES]; 3],
    /// `P` and `sum s^2 l l^T`, symmetric (xx, xy, xz, yy, yz, zz).
    p: [[T; LANES]; 6],
    cov: [[T; LANES]; 6],
}

impl<T: Real> NoiseSums<T> {
    #[inline(always)]
    pub(super) fn new(weighing: Weighing, (x, y): (usize, usize)) -> Self {
        let own = weighing
            .noise
            .shared_cfa_sample
            .map(|pattern| own_channel(pattern, (x, y)));
        let zero = [T::zero(); LANES];
        NoiseSums {
            weighing,
            own,
            q0: zero,
            q: [zero; 3],
            p: [zero; 6],
            cov: [zero; 6],
        }
    }

    /// Adds one light.
    #[inline(always)]
    pub(super) fn add<const FMA: bool>(&mut self, light: &LightLanes<T>) {
        let w = &self.weighing;
        let (photon, floor) = (T::of(w.noise.photon), T::of(w.noise.floor));
        // Per channel `(w_c s_c)^2 chi_c`: with the inverse falloff squared, the factor of a
        // channel's raw variance in the luminance's (independent channels).
        let mut k = [T::zero(); 3];
        for (c, k) in k.iter_mut().enumerate() {
            let ws = T::of(LUMINANCE_WEIGHTS[c]) * light.scale[c];
            *k = ws * ws * T::of(w.noise.channel_scale[c]);
        }
        // The test variance adds the model error and the f32 storage's rounding of `I`.
        let relative = T::of(w.relative_var + (f32::EPSILON as f64).powi(2) / 12.0);
        let tiny = T::of(f32::MIN_POSITIVE as f64);
        let zero = T::zero();
        let mut var = [zero; LANES];
        for l in 0..LANES {
            let mut sum = zero;
            for c in 0..3 {
                let raw = light.rgb[c][l];
                let raw = if raw > zero { raw } else { zero };
                sum = madd::<T, FMA>(k[c], madd::<T, FMA>(photon, raw, floor), sum);
            }
            let m = light.inv_falloff[l];
            var[l] = sum * m * m;
        }
        if let Some(own) = &self.own {
            // All three channels carry the own sample `v`: the luminance's relative variance
            // is `v`'s.
            // Selects, not an index per lane, and every lane's quotient before the selects:
            // with the division inside the select the compiler branched around it lane by
            // lane, and the loop did not vectorise.
            let [r, g, b] = light.rgb;
            let mut own_value = [zero; LANES];
            let mut shared = [zero; LANES];
            for l in 0..LANES {
                let v = if own[l] == 0 { r[l] } else { b[l] };
                let v = if own[l] == 1 { g[l] } else { v };
                let lum = light.lum[l];
                own_value[l] = v;
                shared[l] = lum * lum * madd::<T, FMA>(photon, v, floor) / (v * v);
            }
            for l in 0..LANES {
                var[l] = if own_value[l] > zero {
                    shared[l]
                } else {
                    var[l]
                };
            }
        }
        // Only the sums asked for: a least-squares solve has no statistic to test, and the
        // adaptive screen without a prediction needs no covariance.
        if w.statistic {
            for l in 0..LANES {
                let keep = light.dropped[l] == zero;
                let lum = light.lum[l];
                let test = madd::<T, FMA>(relative * lum, lum, var[l]) + tiny;
                let weight = if keep { T::one() / test } else { zero };
                let d = [
                    light.direction[0][l],
                    light.direction[1][l],
                    light.direction[2][l],
                ];
                let wl = weight * lum;
                self.q0[l] = madd::<T, FMA>(wl, lum, self.q0[l]);
                for i in 0..3 {
                    self.q[i][l] = madd::<T, FMA>(wl, d[i], self.q[i][l]);
                    for j in i..3 {
                        let e = SYM[i][j];
                        self.p[e][l] = madd::<T, FMA>(weight * d[i], d[j], self.p[e][l]);
                    }
                }
            }
        }
        if w.predict {
            for l in 0..LANES {
                let s2 = if light.dropped[l] == zero {
                    var[l]
                } else {
                    zero
                };
                let d = [
                    light.direction[0][l],
                    light.direction[1][l],
                    light.direction[2][l],
                ];
                for i in 0..3 {
                    for j in i..3 {
                        let e = SYM[i][j];
                        self.cov[e][l] = madd::<T, FMA>(s2 * d[i], d[j], self.cov[e][l]);
                    }
                }
            }
        }
    }

    /// The statistic the adaptive screen tests for a fit to `used` lights whose least-squares
    /// luminance normal is `n` (length `length`): the smaller of the bounded statistics
    /// ([`NoiseSums::bounded_statistic`]) at `n` and at the weighted fit's normal
    /// `P^-1 q`, which minimises the sum. The exact kernel passes a pixel whose least-squares
    /// statistic passes, and else one whose weighted fit's does (`ChiSquare::screen`); the
    /// weighted minimum is at most the exact sum at any normal, so either bound passing means
    /// the exact test passes. Screening the least-squares normal alone (its statistic is
    /// inflated where the lights' variances differ) sent 2.4 % of a clean Lambertian 16 MP
    /// set's pixels to the exact kernel, of which 7 % failed there; now 0.39 %.
    #[inline(always)]
    pub(super) fn statistic(&self, n: &[V<T>; 3], used: &V<T>, length: &V<T>) -> V<T> {
        let at_least_squares = self.bounded_statistic(n, used, length);
        let p = vectors6(&self.p);
        let adj = adjugate(&p);
        let det = p[0] * adj[0] + p[1] * adj[1] + p[2] * adj[2];
        let q = [V(self.q[0]), V(self.q[1]), V(self.q[2])];
        let scaled = apply(&adj, &q);
        let inv_det = V::splat(T::one()) / det;
        let weighted = [
            scaled[0] * inv_det,
            scaled[1] * inv_det,
            scaled[2] * inv_det,
        ];
        let weighted_length = dot(&weighted, &weighted).sqrt();
        let at_weighted = self.bounded_statistic(&weighted, used, &weighted_length);
        // Lane by lane. A singular `P` (a NaN or infinite normal) keeps the least-squares
        // value, and so does a weighted normal more than twice as long as the least-squares
        // one (a nearly singular `P`): the rounding bound assumes the sum's terms are of the
        // size they have at the least-squares normal.
        let mut out = at_least_squares;
        for l in 0..LANES {
            let w = at_weighted.0[l];
            if w < out.0[l] && weighted_length.0[l] <= T::of(2.0) * length.0[l] {
                out.0[l] = w;
            }
        }
        out
    }

    /// The chi-square statistic at the luminance normal `n` (length `length`) of a fit to
    /// `used` lights, plus a bound of how far below the exact kernel's it may lie: the
    /// rounding of the expanded sum (a few units of the kernel's precision times `Q0` per
    /// light; at the least-squares and the weighted normal every term of the sum is within
    /// a few `Q0`) and the tiled directions (each residual `r_k` moved by at most `d = 3 |N|
    /// tile_rad`, so the statistic by at most `2 d sqrt(X sum w) + d^2 sum w`, with
    /// `sum w = trace P` for unit directions).
    #[inline(always)]
    fn bounded_statistic(&self, n: &[V<T>; 3], used: &V<T>, length: &V<T>) -> V<T> {
        let (q0, q) = (V(self.q0), [V(self.q[0]), V(self.q[1]), V(self.q[2])]);
        let p = vectors6(&self.p);
        let pn = apply(&p, n);
        let x = q0 - dot(n, &q) * T::of(2.0) + dot(n, &pn);
        let x = x.max(T::zero());
        let rounding = (*used * T::of(2.0) + T::of(8.0)) * q0 * T::epsilon();
        let weight_sum = p[0] + p[3] + p[5];
        let d = *length * T::of(3.0 * self.weighing.tile_rad);
        x + rounding + (x * weight_sum).sqrt() * d * T::of(2.0) + d * d * weight_sum
    }

    /// The predicted error (degrees) of the luminance normal `n` (length `length`) whose
    /// normal matrix has the inverse `inv`: `predict::expected_angle_error` for the
    /// covariance `inv (sum s^2 l l^T) inv`, lane by lane.
    #[inline(always)]
    pub(super) fn predicted_deg(&self, inv: &[V<T>; 6], n: &[V<T>; 3], length: &V<T>) -> V<T> {
        let cov = sandwich(inv, &vectors6(&self.cov));
        let inv_length = V::splat(T::one()) / *length;
        let u = [n[0] * inv_length, n[1] * inv_length, n[2] * inv_length];
        // The tangent-plane covariance's trace and determinant: `tr C - u^T C u` and
        // `u^T adj(C) u`, over `|N|^2` and `|N|^4`.
        let cu = apply(&cov, &u);
        let inv_len2 = inv_length * inv_length;
        let trace = (cov[0] + cov[3] + cov[5] - dot(&u, &cu)) * inv_len2;
        let det = dot(&u, &apply(&adjugate(&cov), &u)) * inv_len2 * inv_len2;
        let half = trace * T::of(0.5);
        let spread = (half * half - det).max(T::zero()).sqrt();
        let (l1, l2) = (
            (half + spread).max(T::zero()),
            (half - spread).max(T::zero()),
        );
        let mut out = [T::zero(); LANES];
        for l in 0..LANES {
            let (a, b) = (l1.0[l], l2.0[l]);
            out[l] = if a > T::zero() {
                let ratio = b / a;
                let ratio = if ratio < T::one() { ratio } else { T::one() };
                T::of((2.0 / std::f64::consts::PI).sqrt()) * a.sqrt() * elliptic_e(ratio)
            } else {
                T::zero()
            };
        }
        V(out) * T::of(180.0 / std::f64::consts::PI)
    }
}

/// `E(1 - ratio)`, the complete elliptic integral of the second kind (as
/// `predict::elliptic_e`), by seven steps of the arithmetic-geometric mean: enough for
/// `ratio` down to 1e-12 (quadratic convergence), without a data-dependent loop.
#[inline(always)]
fn elliptic_e<T: Real>(ratio: T) -> T {
    let half = T::of(0.5);
    let (mut a, mut b) = (T::one(), ratio.sqrt());
    let mut sum = half * (T::one() - ratio);
    let mut weight = half;
    for _ in 0..7 {
        let c = half * (a - b);
        (a, b) = (half * (a + b), (a * b).sqrt());
        weight = weight + weight;
        sum += weight * c * c;
    }
    T::of(std::f64::consts::FRAC_PI_2) / a * (T::one() - sum)
}
