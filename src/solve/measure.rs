//! The first link of the solve's chain: one light's usable measurement at a pixel, a pixel's
//! fit, and the plain least-squares fits (normal equations, SVD) every later link starts from.

use nalgebra::{DMatrix, Matrix3, Vector3};

use super::PixelFit;

/// One light's usable measurement at one pixel, already divided by the light's intensity.
#[derive(Clone, Copy)]
pub(super) struct Measurement {
    /// Unit direction toward the light.
    pub l: Vector3<f64>,
    /// `I'` per colour channel: measured value over the white-surface signal.
    pub rgb: [f64; 3],
    /// Luminance of `rgb`.
    pub lum: f64,
    /// Noise variance of `lum`.
    pub var: f64,
    /// The variance the chi-square test and the weighted fits use (`chi_square::ChiSquare::prepare`).
    pub test_var: f64,
    /// Which light (frame index).
    pub light: u16,
}

/// The solution at one pixel, before it is turned into outputs.
#[derive(Clone)]
pub(super) struct Fit {
    /// Scaled normals (unit normal times albedo): luminance first, then R, G, B.
    pub n_lum: Vector3<f64>,
    pub n_rgb: [Vector3<f64>; 3],
    /// `(L^T L)^-1`, for the predicted error; `(L^T W L)^-1` when `weighted`.
    pub a_inv: Matrix3<f64>,
    /// Weighted least squares with `W = 1 / variance`: `a_inv` is then the covariance of
    /// `n_lum` itself.
    pub weighted: bool,
    pub condition: f64,
    /// RMS luminance residual when the fit's model is not `n_lum . l` (the sheen fit).
    pub residual: Option<f64>,
    pub kind: PixelFit,
}

/// Least squares through the normal equations, inverted in closed form.
pub(super) fn fit_normal_equations(measurements: &[Measurement]) -> Option<Fit> {
    let mut a = Gram::default();
    let mut b_lum = Vector3::zeros();
    let mut b_rgb = [Vector3::zeros(); 3];
    for m in measurements {
        a.add(&m.l, 1.0);
        b_lum += m.l * m.lum;
        for c in 0..3 {
            b_rgb[c] += m.l * m.rgb[c];
        }
    }
    let a = a.matrix();
    let a_inv = a.try_inverse()?;
    let condition = condition_from(&a, &a_inv);
    Some(Fit {
        n_lum: a_inv * b_lum,
        n_rgb: b_rgb.map(|b| a_inv * b),
        a_inv,
        condition,
        residual: None,
        kind: PixelFit::LeastSquares,
        weighted: false,
    })
}

/// The unweighted least squares of the luminance alone: [`fit_normal_equations`]' `n_lum`,
/// `a_inv` and `condition` to the bit (the same sums in the same order, the same inverse;
/// `None` where it gives `None`), without its colour solves.
pub(super) struct LuminanceFit {
    pub n_lum: Vector3<f64>,
    pub a_inv: Matrix3<f64>,
    /// As [`condition_of`] gives it for the same lights.
    pub condition: f64,
}

pub(super) fn fit_luminance(measurements: &[Measurement]) -> Option<LuminanceFit> {
    let mut a = Gram::default();
    let mut b_lum = Vector3::zeros();
    for m in measurements {
        a.add(&m.l, 1.0);
        b_lum += m.l * m.lum;
    }
    let a = a.matrix();
    let a_inv = a.try_inverse()?;
    Some(LuminanceFit {
        n_lum: a_inv * b_lum,
        a_inv,
        condition: condition_from(&a, &a_inv),
    })
}

/// Least squares through the singular value decomposition of `L` (the seed's method).
pub(super) fn fit_svd(measurements: &[Measurement]) -> Option<Fit> {
    let m = measurements.len();
    let l = DMatrix::from_fn(m, 3, |r, c| measurements[r].l[c]);
    let rhs = DMatrix::from_fn(m, 4, |r, c| match c {
        0 => measurements[r].lum,
        _ => measurements[r].rgb[c - 1],
    });
    let svd = l.svd(true, true);
    let sigma = &svd.singular_values;
    if sigma.iter().any(|&s| !(s > 0.0 && s.is_finite())) {
        return None;
    }
    let solution = svd.solve(&rhs, 0.0).ok()?;
    let v_t = svd.v_t.as_ref()?;
    // (L^T L)^-1 = V diag(1/sigma^2) V^T.
    let mut a_inv = Matrix3::zeros();
    for (k, s) in sigma.iter().enumerate() {
        let v = Vector3::new(v_t[(k, 0)], v_t[(k, 1)], v_t[(k, 2)]);
        a_inv += v * v.transpose() / (s * s);
    }
    let norm_a: f64 = sigma.iter().map(|s| s.powi(4)).sum::<f64>().sqrt();
    let norm_a_inv: f64 = sigma.iter().map(|s| s.powi(-4)).sum::<f64>().sqrt();
    let column = |c: usize| Vector3::new(solution[(0, c)], solution[(1, c)], solution[(2, c)]);
    Some(Fit {
        n_lum: column(0),
        n_rgb: [column(1), column(2), column(3)],
        a_inv,
        condition: (norm_a * norm_a_inv).sqrt(),
        residual: None,
        kind: PixelFit::LeastSquares,
        weighted: false,
    })
}

/// Condition number of the lights' (unweighted) matrix, as the kernel reports it.
pub(super) fn condition_of(measurements: &[Measurement]) -> f64 {
    let mut gram = Gram::default();
    for m in measurements {
        gram.add(&m.l, 1.0);
    }
    let a = gram.matrix();
    a.try_inverse()
        .map_or(f64::INFINITY, |inv| condition_from(&a, &inv))
}

/// The Frobenius-norm condition number of `A = L^T L` from `A` and its inverse,
/// square-rooted to speak of `L`: one definition for every fit, so that [`fit_luminance`]'s
/// equals [`fit_normal_equations`]' and [`condition_of`]'s to the bit.
fn condition_from(a: &Matrix3<f64>, a_inv: &Matrix3<f64>) -> f64 {
    (a.norm() * a_inv.norm()).sqrt()
}

/// A running sum of weighted outer products `w l l^T` of light directions, its six distinct
/// entries only: the fits' inner loops ran over all nine. Each entry is summed in the order
/// the full outer products summed it (and `x * y == y * x` exactly), so [`Gram::matrix`] is
/// the same matrix to the bit.
#[derive(Clone, Copy, Default)]
pub(super) struct Gram {
    xx: f64,
    xy: f64,
    xz: f64,
    yy: f64,
    yz: f64,
    zz: f64,
}

impl Gram {
    /// Adds `w l l^T` (a weight of 1 adds `l l^T` exactly).
    #[inline(always)]
    pub fn add(&mut self, l: &Vector3<f64>, w: f64) {
        self.xx += l.x * l.x * w;
        self.xy += l.x * l.y * w;
        self.xz += l.x * l.z * w;
        self.yy += l.y * l.y * w;
        self.yz += l.y * l.z * w;
        self.zz += l.z * l.z * w;
    }

    /// The symmetric matrix.
    #[inline(always)]
    pub fn matrix(&self) -> Matrix3<f64> {
        Matrix3::new(
            self.xx, self.xy, self.xz, self.xy, self.yy, self.yz, self.xz, self.yz, self.zz,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The six-entry sum is the sum of full outer products, bit for bit, weighted or not.
    #[test]
    fn the_gram_sum_is_the_outer_products_sum() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(9);
        for _ in 0..100 {
            let lights: Vec<(Vector3<f64>, f64)> = (0..rng.gen_range(1..40))
                .map(|_| {
                    let l = Vector3::new(
                        rng.gen_range(-1.0..1.0),
                        rng.gen_range(-1.0..1.0),
                        rng.gen_range(0.0..1.0),
                    );
                    (l, rng.gen_range(0.01..1e6))
                })
                .collect();
            for weighted in [false, true] {
                let mut full = Matrix3::zeros();
                let mut gram = Gram::default();
                for (l, w) in &lights {
                    if weighted {
                        full += l * l.transpose() * *w;
                        gram.add(l, *w);
                    } else {
                        full += l * l.transpose();
                        gram.add(l, 1.0);
                    }
                }
                let got = gram.matrix();
                for (a, b) in got.iter().zip(full.iter()) {
                    assert_eq!(a.to_bits(), b.to_bits(), "{got} vs {full}");
                }
            }
        }
    }
}
