//! The robust fit where the sensor model does not explain the residuals (real surfaces: a
//! diffuse lobe that is not quite Lambertian, inter-reflection, shadow edges, highlights), so
//! the chi-square test fails at every pixel and a light's departure cannot be judged in units
//! of sensor noise. The scale of a departure then comes from the pixel's own residuals (the
//! MAD: half the lights may be outliers before it breaks), and a light is an outlier when it
//! departs by several of those scales: below the prediction (a shadow only darkens) or above
//! it (a highlight only brightens), each with its own limit, or when the fit predicts it in
//! attached shadow (its reading is then not linear in the normal).
//!
//! The start must already be robust, or the residuals' scale and signs are those of a wrong
//! normal: with few lights every minimal subset of three is tried (least median of squares,
//! as RANSAC-style photometric stereo does; 120 triples of 10 lights), with more the readings
//! are trimmed at both ends first.

use nalgebra::Vector3;

use super::measure::{fit_normal_equations, Fit, Gram, Measurement};
use super::PixelFit;
use crate::math::MAD_TO_SIGMA;

/// Tuning of the data-scaled fit (fixed from the method, not fitted to any data set).
#[derive(Clone, Copy, Debug)]
pub(super) struct Departures {
    /// The sensor model explains a pixel whose residual scale (MAD) is at most this many of its
    /// noise standard deviations: the noise-model rejection then decides.
    pub model_scale_factor: f64,
    /// A light darker than the prediction by more than this many scales is shadowed.
    pub dark_limit: f64,
    /// A light brighter than the prediction by more than this many scales is a highlight.
    pub bright_limit: f64,
    /// A light whose predicted shading `n . l` is at or below this is treated as unlit.
    pub min_shading: f64,
    /// Try every minimal subset up to this many lights; trim the readings above.
    pub exhaustive_lights: usize,
    /// Trimmed start: fraction of readings dropped at each end.
    pub trim: f64,
}

impl Default for Departures {
    fn default() -> Self {
        Departures {
            // A residual scale within three noise deviations is one the noise model explains.
            model_scale_factor: 3.0,
            // Two scales either way: the iteration re-estimates the scale from the lights it
            // keeps, so the limits trim a contaminated pixel toward its consistent core.
            dark_limit: 2.0,
            bright_limit: 2.0,
            // Within 6 degrees of grazing (n . l <= 0.1) a reading is dominated by what the
            // Lambertian model gets wrong (terminator, rough diffuse fall-off, penumbra).
            min_shading: 0.1,
            exhaustive_lights: 12,
            trim: 0.2,
        }
    }
}

/// Rounds of rejection and refit; the inlier set settles in a few.
const ROUNDS: usize = 10;

/// The residual scale of `g` over the lights it predicts lit: `MAD_TO_SIGMA` times the median
/// absolute residual. `scratch` is reused.
fn residual_scale(measurements: &[Measurement], g: &Vector3<f64>, scratch: &mut Vec<f64>) -> f64 {
    scratch.clear();
    scratch.extend(
        measurements
            .iter()
            .filter(|m| g.dot(&m.l) > 0.0)
            .map(|m| (m.lum - g.dot(&m.l)).abs()),
    );
    median(scratch) * MAD_TO_SIGMA
}

/// The median (the upper one of an even count) in `f64::total_cmp`'s order; infinite for
/// none. `values` is reordered.
fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return f64::INFINITY;
    }
    let mid = values.len() / 2;
    if values.len() <= SMALL_MEDIAN {
        return small_median(values, mid);
    }
    let (_, m, _) = values.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m
}

/// Up to this many values (a pixel's lights, in the usual rigs) the median comes from an
/// insertion sort of integer keys: the data-scaled fit takes several medians per pixel, and
/// the general selection's overhead on ten values was a twentieth of the exact kernel's time.
const SMALL_MEDIAN: usize = 16;

/// The `mid`-th smallest of at most [`SMALL_MEDIAN`] values in `f64::total_cmp`'s order: each
/// value's key is the integer that order compares ([`total_order_key`]), so equal keys are
/// equal values and the result is the selection's.
fn small_median(values: &[f64], mid: usize) -> f64 {
    let mut keys = [0i64; SMALL_MEDIAN];
    for (k, &v) in values.iter().enumerate() {
        let value = total_order_key(v.to_bits() as i64);
        let mut at = k;
        while at > 0 && keys[at - 1] > value {
            keys[at] = keys[at - 1];
            at -= 1;
        }
        keys[at] = value;
    }
    debug_assert!(mid < values.len());
    // The key map is its own inverse.
    f64::from_bits(total_order_key(keys[mid]) as u64)
}

/// `f64::total_cmp`'s integer key of a value's bits: the magnitude bits flipped for negative
/// values. Applied to a key it gives the bits back.
fn total_order_key(bits: i64) -> i64 {
    bits ^ (((bits >> 63) as u64) >> 1) as i64
}

/// The most lights [`best_triple`] searches (its readings are kept in arrays of this size).
const MAX_TRIPLE_LIGHTS: usize = 16;

/// The scaled normal of the least median of squares over every triple of lights (at most
/// [`MAX_TRIPLE_LIGHTS`]; `None` above that or when every triple is singular).
///
/// With 10 lights that is 120 triples per pixel, the data-scaled fit's main cost, so each
/// triple is solved by Cramer's rule from cross products taken once per pair, and its median
/// is only computed when it can win: the median of `m` residuals is below the best so far
/// exactly when more than `m / 2` of them are, which a count answers without selecting. The
/// count runs over blocks of [`LANES`] lights in vector registers, on AVX2 where the CPU has
/// it (the same arithmetic in the same order: the same triple wins).
fn best_triple(measurements: &[Measurement], scratch: &mut Vec<f64>) -> Option<Vector3<f64>> {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked above; the standard library caches the check).
        return unsafe { best_triple_avx2(measurements, scratch) };
    }
    search_triples::<false>(measurements, scratch)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn best_triple_avx2(
    measurements: &[Measurement],
    scratch: &mut Vec<f64>,
) -> Option<Vector3<f64>> {
    search_triples::<true>(measurements, scratch)
}

/// Lights per block of the residual count (four f64 fill an AVX2 register).
const LANES: usize = 4;

/// The readings one array per coordinate, padded past the last light with a NaN reading
/// (whose residual is NaN, below no score), so that the count runs over whole blocks.
struct TripleLights {
    x: [f64; MAX_TRIPLE_LIGHTS],
    y: [f64; MAX_TRIPLE_LIGHTS],
    z: [f64; MAX_TRIPLE_LIGHTS],
    lum: [f64; MAX_TRIPLE_LIGHTS],
    blocks: usize,
}

impl TripleLights {
    #[inline(always)]
    fn new(measurements: &[Measurement]) -> Self {
        let mut lights = TripleLights {
            x: [0.0; MAX_TRIPLE_LIGHTS],
            y: [0.0; MAX_TRIPLE_LIGHTS],
            z: [0.0; MAX_TRIPLE_LIGHTS],
            lum: [f64::NAN; MAX_TRIPLE_LIGHTS],
            blocks: measurements.len().div_ceil(LANES),
        };
        for (k, r) in measurements.iter().enumerate() {
            lights.x[k] = r.l.x;
            lights.y[k] = r.l.y;
            lights.z[k] = r.l.z;
            lights.lum[k] = r.lum;
        }
        lights
    }

    /// `|lum_k - g . l_k|`, in the order `Vector3::dot` sums.
    #[inline(always)]
    fn residual(&self, g: &Vector3<f64>, k: usize) -> f64 {
        (self.lum[k] - (g.x * self.x[k] + g.y * self.y[k] + g.z * self.z[k])).abs()
    }

    /// How many lights `g` fits with a residual below `score`.
    #[inline(always)]
    fn count_below(&self, g: &Vector3<f64>, score: f64) -> usize {
        (0..self.blocks * LANES)
            .filter(|&k| self.residual(g, k) < score)
            .count()
    }

    /// [`TripleLights::count_below`] four lights at a time: the same products and sums in the
    /// same order, so the same count.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn count_below_avx2(&self, g: &Vector3<f64>, score: f64) -> usize {
        use std::arch::x86_64::*;
        let (gx, gy, gz) = (
            _mm256_set1_pd(g.x),
            _mm256_set1_pd(g.y),
            _mm256_set1_pd(g.z),
        );
        let score = _mm256_set1_pd(score);
        let sign = _mm256_set1_pd(-0.0);
        let mut below = 0;
        for block in 0..self.blocks {
            let at = block * LANES;
            // SAFETY: `blocks * LANES <= MAX_TRIPLE_LIGHTS`, the arrays' length.
            let load = |lane: &[f64; MAX_TRIPLE_LIGHTS]| _mm256_loadu_pd(lane.as_ptr().add(at));
            let dot = _mm256_add_pd(
                _mm256_add_pd(
                    _mm256_mul_pd(gx, load(&self.x)),
                    _mm256_mul_pd(gy, load(&self.y)),
                ),
                _mm256_mul_pd(gz, load(&self.z)),
            );
            let residual = _mm256_andnot_pd(sign, _mm256_sub_pd(load(&self.lum), dot));
            // Ordered compare: a padded lane's NaN is below nothing.
            let mask = _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LT_OQ>(residual, score));
            below += mask.count_ones() as usize;
        }
        below
    }
}

/// The search of [`best_triple`]; `AVX2` counts with AVX2 instructions (only called so from
/// [`best_triple_avx2`]).
#[inline(always)]
fn search_triples<const AVX2: bool>(
    measurements: &[Measurement],
    scratch: &mut Vec<f64>,
) -> Option<Vector3<f64>> {
    let m = measurements.len();
    if m > MAX_TRIPLE_LIGHTS {
        return None;
    }
    let mid = m / 2;
    let lights = TripleLights::new(measurements);
    let mut crosses = [[Vector3::zeros(); MAX_TRIPLE_LIGHTS]; MAX_TRIPLE_LIGHTS];
    for a in 0..m {
        for b in a + 1..m {
            crosses[a][b] = measurements[a].l.cross(&measurements[b].l);
        }
    }
    let mut best: Option<(f64, Vector3<f64>)> = None;
    for a in 0..m {
        for b in a + 1..m {
            let ab = crosses[a][b];
            for c in b + 1..m {
                let det = measurements[c].l.dot(&ab);
                if det.abs() <= f64::EPSILON {
                    continue;
                }
                // Rows la, lb, lc: the inverse's columns are lb x lc, lc x la, la x lb.
                let g = (crosses[b][c] * measurements[a].lum - crosses[a][c] * measurements[b].lum
                    + ab * measurements[c].lum)
                    / det;
                if let Some((score, _)) = best {
                    #[cfg(target_arch = "x86_64")]
                    let below = if AVX2 {
                        // SAFETY: only `best_triple_avx2`, compiled for and called on AVX2,
                        // instantiates `AVX2 = true`.
                        unsafe { lights.count_below_avx2(&g, score) }
                    } else {
                        lights.count_below(&g, score)
                    };
                    #[cfg(not(target_arch = "x86_64"))]
                    let below = lights.count_below(&g, score);
                    if below <= mid {
                        continue;
                    }
                }
                scratch.clear();
                scratch.extend((0..m).map(|k| lights.residual(&g, k)));
                best = Some((median(scratch), g));
            }
        }
    }
    best.map(|(_, g)| g)
}

/// Least squares on the readings left after dropping `trim` of them at each end. The
/// readings are ordered through `order` (brightness and position) rather than moved: the same
/// stable order, so the same sums as sorting the readings themselves.
fn trimmed_start(
    measurements: &[Measurement],
    trim: f64,
    order: &mut Vec<(f64, u16)>,
) -> Option<Vector3<f64>> {
    order.clear();
    order.extend(
        measurements
            .iter()
            .enumerate()
            .map(|(k, m)| (m.lum, k as u16)),
    );
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    let n = order.len();
    let drop = ((trim * n as f64).round() as usize).min(n.saturating_sub(4) / 2);
    luminance_normal(
        order[drop..n - drop]
            .iter()
            .map(|&(_, k)| &measurements[k as usize]),
    )
}

/// The least-squares luminance normal of `measurements` alone, as `fit_normal_equations`
/// computes it (the same sums in the same order, the same inverse: the same bits, and `None`
/// where it gives `None`) without the colour, condition and covariance the data-scaled fit's
/// rounds do not use.
fn luminance_normal<'a>(
    measurements: impl Iterator<Item = &'a Measurement>,
) -> Option<Vector3<f64>> {
    let mut a = Gram::default();
    let mut b = Vector3::zeros();
    for m in measurements {
        a.add(&m.l, 1.0);
        b += m.l * m.lum;
    }
    Some(a.matrix().try_inverse()? * b)
}

/// The data-scaled fit's buffers, reused across pixels.
#[derive(Default)]
pub(super) struct Buffers {
    /// Every usable light while the rounds keep a subset.
    all: Vec<Measurement>,
    /// The lights a round keeps.
    candidate: Vec<Measurement>,
    /// Residuals and variances for the medians.
    scratch: Vec<f64>,
    /// The trimmed start's order of the readings.
    order: Vec<(f64, u16)>,
}

/// The data-scaled fit of `measurements`, or `None` where the sensor model explains the
/// residuals (or no robust start exists): the caller's noise-model rejection decides there.
/// On success leaves the kept lights in `measurements`, on `None` every light as it came.
pub(super) fn fit(
    tuning: &Departures,
    measurements: &mut Vec<Measurement>,
    buffers: &mut Buffers,
    least_squares: &Vector3<f64>,
) -> Option<Fit> {
    let Buffers {
        all,
        candidate,
        scratch,
        order,
    } = buffers;
    let m = measurements.len();
    if m < 5 {
        return None;
    }
    // The trimmed fit decides cheaply whether the noise model explains the pixel; only then
    // are the minimal subsets searched for the start.
    let trimmed = trimmed_start(measurements, tuning.trim, order).unwrap_or(*least_squares);
    let scale = residual_scale(measurements, &trimmed, scratch);
    // The median deviation is the root of the median variance (the root is monotone).
    scratch.clear();
    scratch.extend(measurements.iter().map(|m| m.test_var));
    let noise = median(scratch).sqrt();
    if scale.is_nan() || scale <= tuning.model_scale_factor * noise {
        return None;
    }
    let start = if m <= tuning.exhaustive_lights {
        best_triple(measurements, scratch)?
    } else {
        trimmed
    };
    let mut scale = residual_scale(measurements, &start, scratch);
    all.clear();
    all.extend_from_slice(measurements);
    let mut g = start;
    // Whether a round fitted a subset (then left in `measurements`); the rounds need only
    // its luminance normal, the full fit is taken once at the end.
    let mut fitted = false;
    // The residual scale of the latest fit on its own lights (before the noise floor).
    let mut fitted_scale = f64::INFINITY;
    for _ in 0..ROUNDS {
        let albedo = g.norm();
        candidate.clear();
        candidate.extend(all.iter().filter(|m| {
            let shading = g.dot(&m.l);
            let r = m.lum - shading;
            shading > tuning.min_shading * albedo
                && r >= -tuning.dark_limit * scale
                && r <= tuning.bright_limit * scale
        }));
        if candidate.len() < 4 || (fitted && same_lights(candidate, measurements)) {
            // Too few lights, or the same lights as the fit already has: settled.
            break;
        }
        let Some(normal) = luminance_normal(candidate.iter()) else {
            break;
        };
        std::mem::swap(measurements, candidate);
        g = normal;
        fitted = true;
        fitted_scale = residual_scale(measurements, &g, scratch);
        scale = fitted_scale.max(noise);
    }
    // Judged on the lights the fit kept: where the noise model explains their residuals, the
    // pixel's departures are outliers against a model that holds (cast shadows on a
    // Lambertian surface), and the noise-model rejection judges them more finely than a scale
    // taken from the data (the early test above can only look at all lights, whose MAD a
    // contaminated start inflates).
    let explained = fitted && fitted_scale <= tuning.model_scale_factor * noise;
    // The last round's lights invert as they did in the round.
    let result = (fitted && !explained)
        .then(|| fit_normal_equations(measurements))
        .flatten();
    match result {
        Some(mut fit) => {
            fit.kind = if measurements.len() < all.len() {
                PixelFit::Robust
            } else {
                PixelFit::LeastSquares
            };
            Some(fit)
        }
        None => {
            measurements.clear();
            measurements.extend_from_slice(all);
            None
        }
    }
}

/// True when both hold the same lights (in the same order, as filtering `all` leaves them).
fn same_lights(a: &[Measurement], b: &[Measurement]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.light == y.light)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Ten lights on a cone around the view, readings `albedo * n.l` times `1 + e_k` with a
    /// deterministic +-`scatter` pattern, and a per-light noise deviation `noise`.
    fn pixel(normal: Vector3<f64>, scatter: f64, noise: f64) -> Vec<Measurement> {
        (0..10)
            .map(|k| {
                let a = k as f64 * 0.628;
                let l = Vector3::new(a.cos() * 0.6, a.sin() * 0.6, 0.8).normalize();
                let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
                let lum = 0.5 * normal.dot(&l) * (1.0 + sign * scatter);
                Measurement {
                    l,
                    rgb: [lum; 3],
                    lum,
                    var: noise * noise,
                    test_var: noise * noise,
                    light: k as u16,
                }
            })
            .collect()
    }

    fn solve(measurements: &mut Vec<Measurement>) -> Option<Fit> {
        let ls = fit_normal_equations(measurements).unwrap().n_lum;
        fit(
            &Departures::default(),
            measurements,
            &mut Buffers::default(),
            &ls,
        )
    }

    #[test]
    fn drops_a_shadow_and_a_highlight_under_model_error() {
        let normal = Vector3::new(0.2, -0.1, 0.97).normalize();
        // 1 % model error, far above the noise (1e-5): the data set the scale.
        let mut m = pixel(normal, 0.01, 1e-5);
        m[3].lum *= 0.1;
        m[7].lum += 0.3;
        let fit = solve(&mut m).expect("the noise model does not explain 1 % scatter");
        let kept: Vec<u16> = m.iter().map(|m| m.light).collect();
        assert!(!kept.contains(&3) && !kept.contains(&7), "{kept:?}");
        assert_eq!(fit.kind, PixelFit::Robust);
        // A 1 % reading error moves the normal by about 0.01 rad / sqrt(lights / 3) ~ 0.33
        // deg with 8 lights; 4x that bounds it.
        let angle = fit.n_lum.normalize().angle(&normal).to_degrees();
        assert!(angle < 1.3, "{angle}");
    }

    /// The counting shortcut and Cramer's rule pick the same triple as the plain search: every
    /// triple solved by matrix inversion and its median taken by sorting.
    #[test]
    fn the_fast_triple_search_finds_the_plain_searchs_minimum() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
        for _ in 0..50 {
            let normal =
                Vector3::new(rng.gen_range(-0.5..0.5), rng.gen_range(-0.5..0.5), 1.0).normalize();
            let mut m = pixel(normal, 0.02, 1e-5);
            for r in m.iter_mut() {
                // Shadows and highlights at random, so the minimum is not the first triple.
                r.lum *= rng.gen_range(0.3..1.6);
            }
            let plain = (0..m.len())
                .flat_map(|a| {
                    (a + 1..m.len()).flat_map(move |b| (b + 1..10).map(move |c| [a, b, c]))
                })
                .filter_map(|t| {
                    let rows = t.map(|k| m[k].l.transpose());
                    let g = nalgebra::Matrix3::from_rows(&rows).try_inverse()?
                        * Vector3::from(t.map(|k| m[k].lum));
                    let mut r: Vec<f64> = m.iter().map(|x| (x.lum - g.dot(&x.l)).abs()).collect();
                    r.sort_by(f64::total_cmp);
                    Some((r[m.len() / 2], g))
                })
                .fold(
                    None,
                    |best: Option<(f64, Vector3<f64>)>, (s, g)| match best {
                        Some((b, _)) if b <= s => best,
                        _ => Some((s, g)),
                    },
                )
                .unwrap()
                .1;
            let fast = best_triple(&m, &mut Vec::new()).unwrap();
            assert!(
                (fast - plain).norm() <= 1e-9 * plain.norm(),
                "{fast} vs {plain}"
            );
            // The portable count picks the same triple as the one `best_triple` dispatched to.
            let portable = search_triples::<false>(&m, &mut Vec::new()).unwrap();
            assert_eq!(portable, fast);
        }
    }

    /// The small-count median is the general selection's value, signed zeros, infinities and
    /// NaNs included.
    #[test]
    fn the_small_median_is_the_selections() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        let specials = [
            0.0,
            -0.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            -f64::NAN,
        ];
        for n in 1..=SMALL_MEDIAN {
            for _ in 0..200 {
                let values: Vec<f64> = (0..n)
                    .map(|_| match rng.gen_range(0..4) {
                        0 => specials[rng.gen_range(0..specials.len())],
                        1 => rng.gen_range(-1.0..1.0) * 1e-300,
                        _ => rng.gen_range(-5.0..5.0),
                    })
                    .collect();
                let mut selected = values.clone();
                let expected = *selected.select_nth_unstable_by(n / 2, f64::total_cmp).1;
                let got = small_median(&values, n / 2);
                assert_eq!(got.to_bits(), expected.to_bits(), "{values:?}");
            }
        }
    }

    #[test]
    fn leaves_pixels_the_noise_model_explains_to_it() {
        let normal = Vector3::new(-0.3, 0.2, 0.93).normalize();
        // The scatter (0.1 % of ~0.45) is within the noise deviation (1e-3).
        let mut m = pixel(normal, 0.001, 1e-3);
        m[5].lum *= 0.2;
        assert!(solve(&mut m).is_none());
        assert_eq!(m.len(), 10);
    }
}
