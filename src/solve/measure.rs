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
    let mut a = Matrix3::zeros();
    let mut b_lum = Vector3::zeros();
    let mut b_rgb = [Vector3::zeros(); 3];
    for m in measurements {
        a += m.l * m.l.transpose();
        b_lum += m.l * m.lum;
        for c in 0..3 {
            b_rgb[c] += m.l * m.rgb[c];
        }
    }
    let a_inv = a.try_inverse()?;
    // Frobenius-norm condition number of A = L^T L, square-rooted to speak of L.
    let condition = (a.norm() * a_inv.norm()).sqrt();
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
    let a: Matrix3<f64> = measurements.iter().map(|m| m.l * m.l.transpose()).sum();
    a.try_inverse()
        .map_or(f64::INFINITY, |inv| (a.norm() * inv.norm()).sqrt())
}
