//! The sheen fit: a pixel of velvet-like cloth fitted with the cloth BRDF of seed 004 (eqs.
//! 21-23) instead of the Lambertian model, solving for the normal and the diffuse albedo while
//! the lobe's shape (its Fresnel colour `f0`, width `alpha` and grazing amplitude) is a
//! property of the material, given.
//!
//! With `F = f0 + (1 - f0) s`, `s = (1 - v.h)^5` and `g = pi D(n.h) (n.l) / (4 (n.l + n.v -
//! (n.l)(n.v)))`, one light's normalised reading is `kd (1 - F)(n.l) + F g`: linear in the
//! albedo `kd` for a given normal. The fit therefore searches the normal only (two tangent-plane
//! parameters, Gauss-Newton with forward differences, from the least-squares normal) with the
//! albedo solved in closed form at each step (variable projection). The cost has several
//! minima over the hemisphere, so where few lights are left (6 or fewer) or the first minimum
//! fails the chi-square test, descents also start from the lowest normals of a search over the
//! hemisphere (with few lights the best five of 544, else the best of 256) and the lowest
//! minimum wins. It runs only on pixels the robust fit escalates
//! to it, so its cost is per escalated pixel.
//!
//! On the synthetic sheen scene the renderer uses this same model, so the fit's gain there is
//! partly by construction; the README reports the robust fit without it beside it.

use nalgebra::{Matrix2, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::chi_square::ChiSquare;
use super::measure::{Fit, Measurement};
use super::predict::tangent_basis;
use super::{PixelFit, LUMINANCE_WEIGHTS};
use crate::error::{Error, Result};

/// The material's sheen lobe (seed eq. 21-23 parameters).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SheenModel {
    /// Fresnel reflectance at normal incidence per colour channel (the sheen colour).
    pub f0: [f64; 3],
    /// Width of the inverted Gaussian.
    pub alpha: f64,
    /// Amplitude of the grazing peak.
    pub amplitude: f64,
}

impl Default for SheenModel {
    /// The synthetic velvet's lobe (the renderer's `synth::Sheen` is this type), Ashikhmin's
    /// amplitude 4.
    fn default() -> Self {
        SheenModel {
            f0: [0.35; 3],
            alpha: 0.4,
            amplitude: 4.0,
        }
    }
}

impl SheenModel {
    /// Checks the lobe is physical: every `f0` in [0, 1), `alpha` positive and `amplitude` not
    /// negative, all finite; the error names the values.
    pub fn validate(&self) -> Result<()> {
        let f0_ok = self.f0.iter().all(|f| (0.0..1.0).contains(f));
        let alpha_ok = self.alpha > 0.0 && self.alpha.is_finite();
        let amplitude_ok = self.amplitude >= 0.0 && self.amplitude.is_finite();
        if f0_ok && alpha_ok && amplitude_ok {
            Ok(())
        } else {
            Err(Error::Invalid(format!(
                "sheen model needs f0 in [0, 1), alpha > 0 and amplitude >= 0, got {self:?}"
            )))
        }
    }

    /// Seed eq. 22: the inverted-Gaussian distribution at half-vector cosine `cos_h`.
    pub fn distribution(&self, cos_h: f64) -> f64 {
        let a2 = self.alpha * self.alpha;
        let norm = 1.0 / (std::f64::consts::PI * (1.0 + self.amplitude * a2));
        let sin2 = (1.0 - cos_h * cos_h).max(0.0);
        if sin2 < 1e-12 {
            // exp(-cot^2/a^2) vanishes far faster than sin^4 does.
            return norm;
        }
        let cot2 = cos_h * cos_h / sin2;
        norm * (1.0 + self.amplitude * (-cot2 / a2).exp() / (sin2 * sin2))
    }

    /// For a light at `l`: `(diffuse, sheen)` with the reading `kd * diffuse + sheen`, for
    /// Fresnel reflectance `f0`. Zero when the light is behind the surface.
    pub fn terms(
        &self,
        f0: f64,
        n: &Vector3<f64>,
        l: &Vector3<f64>,
        v: &Vector3<f64>,
    ) -> (f64, f64) {
        self.terms_at(&LightGeometry::new(f0, l, v), n, v)
    }

    /// `terms` with the normal-independent part precomputed.
    #[inline]
    fn terms_at(&self, light: &LightGeometry, n: &Vector3<f64>, v: &Vector3<f64>) -> (f64, f64) {
        let nl = n.dot(&light.l);
        if nl <= 0.0 {
            return (0.0, 0.0);
        }
        let nv = n.dot(v).max(0.0);
        let d = self.distribution(n.dot(&light.h).clamp(-1.0, 1.0));
        let g = std::f64::consts::PI * d * nl / (4.0 * (nl + nv - nl * nv));
        ((1.0 - light.fresnel) * nl, light.fresnel * g)
    }

    fn luminance_f0(&self) -> f64 {
        (0..3).map(|c| LUMINANCE_WEIGHTS[c] * self.f0[c]).sum()
    }
}

/// What a light's sheen terms need that does not depend on the normal.
#[derive(Clone, Copy, Default)]
struct LightGeometry {
    l: Vector3<f64>,
    /// Half vector between the light and the view.
    h: Vector3<f64>,
    /// Schlick's Fresnel term at the half vector.
    fresnel: f64,
}

impl LightGeometry {
    fn new(f0: f64, l: &Vector3<f64>, v: &Vector3<f64>) -> Self {
        let h = (l + v).normalize();
        let s = (1.0 - v.dot(&h).clamp(0.0, 1.0)).powi(5);
        LightGeometry {
            l: *l,
            h,
            fresnel: f0 + (1.0 - f0) * s,
        }
    }
}

/// `m` with the sheen lobe at normal `n` taken out: `(reading - sheen) / (1 - F)`, which is
/// `kd (n.l)` where the model holds, so that the Lambertian outlier tests apply to it.
pub(super) fn lambertian_equivalent(
    model: &SheenModel,
    view: &Vector3<f64>,
    n: &Vector3<f64>,
    m: &Measurement,
) -> Measurement {
    let f0 = model.luminance_f0();
    let geometry = LightGeometry::new(f0, &m.l, view);
    let (_, sheen) = model.terms_at(&geometry, n, view);
    let diffuse_share = 1.0 - geometry.fresnel;
    let rgb = std::array::from_fn(|c| {
        let g = LightGeometry::new(model.f0[c], &m.l, view);
        (m.rgb[c] - model.terms_at(&g, n, view).1) / (1.0 - g.fresnel)
    });
    let scale2 = diffuse_share * diffuse_share;
    Measurement {
        lum: (m.lum - sheen) / diffuse_share,
        rgb,
        var: m.var / scale2,
        test_var: m.test_var / scale2,
        ..*m
    }
}

/// The normal `n0` moved by `(u, w)` in its tangent plane.
fn perturbed(
    n0: &Vector3<f64>,
    t: &(Vector3<f64>, Vector3<f64>),
    p: &Vector2<f64>,
) -> Vector3<f64> {
    (n0 + t.0 * p.x + t.1 * p.y).normalize()
}

/// Weighted residuals of the luminance under `model` at normal `n`, albedo in closed form.
/// Returns the albedo; `residuals` gets one entry per measurement.
fn residuals(
    model: &SheenModel,
    problem: &Problem,
    n: &Vector3<f64>,
    residuals: &mut [f64],
) -> f64 {
    let m = problem.measurements.len();
    let mut diffuse = [0.0; MAX_LIGHTS_SHEEN];
    let (mut num, mut den) = (0.0, 0.0);
    for (k, meas) in problem.measurements.iter().enumerate() {
        let (d, sheen) = model.terms_at(&problem.geometry[k], n, &problem.view);
        let w = problem.weights[k];
        num += w * d * (meas.lum - sheen);
        den += w * d * d;
        diffuse[k] = d;
        residuals[k] = sheen;
    }
    let kd = if den > 0.0 { num / den } else { 0.0 };
    for k in 0..m {
        let predicted = kd * diffuse[k] + residuals[k];
        residuals[k] = (problem.measurements[k].lum - predicted) * problem.weights[k].sqrt();
    }
    kd
}

/// One pixel's sheen problem with its normal-independent parts precomputed.
struct Problem<'a> {
    measurements: &'a [Measurement],
    geometry: [LightGeometry; MAX_LIGHTS_SHEEN],
    weights: [f64; MAX_LIGHTS_SHEEN],
    view: Vector3<f64>,
}

const MAX_LIGHTS_SHEEN: usize = 64;
const ITERATIONS: usize = 12;

/// Fits the sheen model to `measurements`, starting from the normal of the Lambertian fit
/// `lambert`. Returns the fit and its chi-square statistic; `None` when it does not converge
/// to a normal facing the camera's side.
pub(super) fn fit(
    model: &SheenModel,
    chi: &ChiSquare,
    view: &Vector3<f64>,
    measurements: &[Measurement],
    lambert: &Fit,
) -> Option<(Fit, f64)> {
    let m = measurements.len();
    if !(4..=MAX_LIGHTS_SHEEN).contains(&m) {
        return None;
    }
    let f0 = model.luminance_f0();
    let mut problem = Problem {
        measurements,
        geometry: [LightGeometry::default(); MAX_LIGHTS_SHEEN],
        weights: [0.0; MAX_LIGHTS_SHEEN],
        view: *view,
    };
    for (k, meas) in measurements.iter().enumerate() {
        problem.geometry[k] = LightGeometry::new(f0, &meas.l, view);
        problem.weights[k] = 1.0 / chi.variance(meas);
    }
    let from_lambert = lambert
        .n_lum
        .try_normalize(1e-12)
        .and_then(|n0| levenberg_marquardt(model, &problem, n0));
    // The Lambertian normal (biased by the lobe, and by any shadowed light) can start the
    // descent in the wrong one of the sheen cost's minima over the hemisphere, most often with
    // few lights: where there are few, or where the minimum found fails the chi-square test,
    // also descend from the best normal of a coarse search and keep the lower minimum.
    let settled = from_lambert
        .as_ref()
        .is_some_and(|(_, cost)| m > GLOBAL_SEARCH_MAX_LIGHTS && chi.accepts_statistic(*cost, m));
    let best = if settled {
        from_lambert
    } else {
        // Few lights: a steep flank, possibly seen at a grazing angle; more lights that fail
        // the test: a shadowed light pulled the first descent off, and the spiral's best
        // normal is enough (the full search on every such pixel cost far more time than the
        // error it saved: docs/solve.md).
        let (normals, starts) = if m <= GLOBAL_SEARCH_MAX_LIGHTS {
            (search_normals(), SEARCH_STARTS)
        } else {
            (&search_normals()[..SPIRAL_COUNT], 1)
        };
        let mut best = from_lambert;
        for n0 in coarse_search(model, &problem, normals, starts)
            .into_iter()
            .flatten()
        {
            if let Some(b) = levenberg_marquardt(model, &problem, n0) {
                if best.as_ref().map_or(true, |a| b.1 < a.1) {
                    best = Some(b);
                }
            }
        }
        best
    };
    let (n, cost) = best?;
    outputs(model, &problem, &n, lambert).map(|fit| (fit, cost))
}

/// Fits with at most this many lights always also start from a coarse search of the
/// hemisphere (more lights: only where the first minimum fails the chi-square test): with so
/// few lights the Lambertian start alone often lands in the wrong minimum (docs/solve.md).
const GLOBAL_SEARCH_MAX_LIGHTS: usize = 6;

/// Normals of the search's spiral (the first of [`search_normals`]).
const SPIRAL_COUNT: usize = 256;

/// Descents started from the search's lowest normals (one start can lie in a narrow basin
/// whose grid point happens to be lower than the true minimum's neighbours).
const SEARCH_STARTS: usize = 5;

/// Heights (`z` of the unit normal) of the search's rings near the horizon.
const HORIZON_RINGS_Z: [f64; 4] = [0.01, 0.035, 0.07, 0.12];
/// Normals per ring near the horizon (5 degrees apart in azimuth).
const HORIZON_RING_COUNT: usize = 72;

/// Normals of the coarse search: a Fibonacci spiral of 256 normals over the hemisphere facing
/// the camera's side (z > 0), about 9 degrees apart, and 4 rings of 72 near the horizon: the
/// spiral alone, with one descent, leaves steep pixels in the wrong minimum (docs/solve.md;
/// `tests/estimators.rs` checks the steep pixels of the synthetic velvet).
fn search_normals() -> &'static [Vector3<f64>] {
    static NORMALS: std::sync::OnceLock<Vec<Vector3<f64>>> = std::sync::OnceLock::new();
    NORMALS.get_or_init(|| {
        const COUNT: usize = SPIRAL_COUNT;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let mut v: Vec<Vector3<f64>> = (0..COUNT)
            .map(|i| {
                // Uniform in z over (0, 1]: equal areas on the hemisphere.
                let z = 1.0 - (i as f64 + 0.5) / COUNT as f64;
                let r = (1.0 - z * z).sqrt();
                let phi = golden * i as f64;
                Vector3::new(r * phi.cos(), r * phi.sin(), z)
            })
            .collect();
        // Steep flanks, seen at grazing angles, where the lobe is far sharper than the
        // spiral's spacing: rings 5 degrees apart in azimuth at 83-89.4 degrees of tilt.
        for z in HORIZON_RINGS_Z {
            let r = (1.0f64 - z * z).sqrt();
            for a in 0..HORIZON_RING_COUNT {
                let phi = std::f64::consts::TAU * a as f64 / HORIZON_RING_COUNT as f64;
                v.push(Vector3::new(r * phi.cos(), r * phi.sin(), z));
            }
        }
        v
    })
}

/// The `starts` (at most [`SEARCH_STARTS`]) of `normals` with the lowest sheen costs and a
/// positive albedo, lowest first.
fn coarse_search(
    model: &SheenModel,
    problem: &Problem,
    normals: &[Vector3<f64>],
    starts: usize,
) -> [Option<Vector3<f64>>; SEARCH_STARTS] {
    let m = problem.measurements.len();
    let mut r = [0.0; MAX_LIGHTS_SHEEN];
    let mut best: [Option<(f64, Vector3<f64>)>; SEARCH_STARTS] = [None; SEARCH_STARTS];
    let best_of = &mut best[..starts.min(SEARCH_STARTS)];
    for n in normals {
        let kd = residuals(model, problem, n, &mut r[..m]);
        if kd.is_nan() || kd <= 0.0 {
            continue;
        }
        let cost: f64 = r[..m].iter().map(|e| e * e).sum();
        // Insertion into the short list, kept sorted by cost: the candidate takes the first
        // slot it beats and carries the one it displaced on down.
        let mut candidate = (cost, *n);
        for slot in best_of.iter_mut() {
            match slot {
                None => {
                    *slot = Some(candidate);
                    break;
                }
                Some(held) if candidate.0 < held.0 => std::mem::swap(held, &mut candidate),
                Some(_) => {}
            }
        }
    }
    best.map(|b| b.map(|(_, n)| n))
}

/// Levenberg-Marquardt over the normal's two tangent-plane parameters from `n0`, the albedo
/// in closed form at each step. Returns the normal and its cost (the chi-square statistic);
/// `None` when it ends on a normal facing away from the camera's side.
fn levenberg_marquardt(
    model: &SheenModel,
    problem: &Problem,
    n0: Vector3<f64>,
) -> Option<(Vector3<f64>, f64)> {
    let m = problem.measurements.len();
    let tangent = tangent_basis(&n0);
    let mut p = Vector2::zeros();
    let mut r = [0.0; MAX_LIGHTS_SHEEN];
    let mut r_step = [0.0; MAX_LIGHTS_SHEEN];
    let mut jac = [[0.0; 2]; MAX_LIGHTS_SHEEN];
    residuals(model, problem, &n0, &mut r[..m]);
    let mut cost: f64 = r[..m].iter().map(|e| e * e).sum();
    let mut damping = 1e-3;
    const H: f64 = 1e-6;
    for _ in 0..ITERATIONS {
        for d in 0..2 {
            let mut q = p;
            q[d] += H;
            residuals(
                model,
                problem,
                &perturbed(&n0, &tangent, &q),
                &mut r_step[..m],
            );
            for k in 0..m {
                jac[k][d] = (r_step[k] - r[k]) / H;
            }
        }
        let mut jtj = Matrix2::zeros();
        let mut jtr = Vector2::zeros();
        for k in 0..m {
            let j = Vector2::new(jac[k][0], jac[k][1]);
            jtj += j * j.transpose();
            jtr += j * r[k];
        }
        // Levenberg-Marquardt: damp until the step lowers the cost.
        let mut improved = false;
        for _ in 0..8 {
            let damped = jtj + Matrix2::from_diagonal(&jtj.diagonal()) * damping;
            let Some(step) = damped.try_inverse().map(|inv| -(inv * jtr)) else {
                damping *= 10.0;
                continue;
            };
            let q = p + step;
            residuals(
                model,
                problem,
                &perturbed(&n0, &tangent, &q),
                &mut r_step[..m],
            );
            let new_cost: f64 = r_step[..m].iter().map(|e| e * e).sum();
            if new_cost < cost {
                p = q;
                r[..m].copy_from_slice(&r_step[..m]);
                let converged = cost - new_cost < 1e-6 * cost || step.norm() < 1e-7;
                cost = new_cost;
                damping = (damping * 0.3).max(1e-9);
                improved = !converged;
                break;
            }
            damping *= 10.0;
        }
        if !improved {
            break;
        }
    }
    let n = perturbed(&n0, &tangent, &p);
    (n.z > 0.0 && cost.is_finite()).then_some((n, cost))
}

/// The fit's normal, albedo and residual in the shape the kernel writes.
fn outputs(model: &SheenModel, problem: &Problem, n: &Vector3<f64>, lambert: &Fit) -> Option<Fit> {
    let measurements = problem.measurements;
    let m = measurements.len();
    let mut r = [0.0; MAX_LIGHTS_SHEEN];
    let kd_lum = residuals(model, problem, n, &mut r[..m]);
    if kd_lum.is_nan() || kd_lum <= 0.0 {
        return None;
    }
    let sum_sq: f64 = (0..m).map(|k| r[k] * r[k] / problem.weights[k]).sum();
    let kd_rgb: [f64; 3] = std::array::from_fn(|c| {
        let (mut num, mut den) = (0.0, 0.0);
        for meas in measurements {
            let (diffuse, sheen) = model.terms(model.f0[c], n, &meas.l, &problem.view);
            num += diffuse * (meas.rgb[c] - sheen);
            den += diffuse * diffuse;
        }
        if den > 0.0 {
            num / den
        } else {
            0.0
        }
    });
    Some(Fit {
        n_lum: n * kd_lum,
        n_rgb: kd_rgb.map(|kd| n * kd),
        a_inv: lambert.a_inv,
        weighted: lambert.weighted,
        condition: lambert.condition,
        residual: Some((sum_sq / m as f64).sqrt()),
        kind: PixelFit::Sheen,
    })
}
