//! Flattening: removes the sample's low-frequency tilt (folds, a table that is not level)
//! from the normal map while keeping the weave. Works on slopes (`-nx/nz`, `-ny/nz`), where
//! tilt is additive: each slope plane minus its Gaussian low-pass (three box passes, mirrored
//! at the borders, so a constant tilt is removed exactly), then back to unit normals.

use rayon::prelude::*;

use super::fft::transpose;
use crate::plane::Plane;

/// Slopes steeper than this (about 84 deg) are clamped before filtering, so a grazing or
/// broken normal cannot smear a large value over its neighbourhood.
const MAX_SLOPE: f32 = 10.0;

/// The Gaussian's standard deviation for a cut-off wavelength of `radius_px`: half of it, so
/// the low-pass passes exp(-pi^2 / 2) < 1 % at the cut-off frequency (detail shorter than the
/// radius is kept) and 98 % at a sixteenth of it (a fold 16 radii long is removed).
pub fn sigma_for_radius(radius_px: f64) -> f64 {
    0.5 * radius_px
}

/// Gain of the flattening (a high-pass) at spatial frequency `f` (cycles per pixel): what
/// fraction of a sinusoidal slope of that frequency is kept. The three-box cascade has the
/// Gaussian's variance, so this is its transfer to within a few per cent.
pub fn kept_fraction(radius_px: f64, f: f64) -> f64 {
    let sigma = sigma_for_radius(radius_px);
    1.0 - (-2.0 * std::f64::consts::PI.powi(2) * sigma * sigma * f * f).exp()
}

/// Flattens the unit normal map `normal` (world frame) in place with cut-off `radius_px`.
/// Only the `solved` pixels (one flag per pixel) take part: the low-pass is a normalised
/// convolution over them (`blur(slope * solved) / blur(solved)`), so the flat normals an
/// unsolved background holds do not pull an object's tilt toward zero near its edge, and
/// unsolved pixels keep the normal they hold.
pub fn flatten(normal: &mut [Plane; 3], solved: &[bool], radius_px: f64) {
    let (w, h) = (normal[0].width, normal[0].height);
    let sigma = sigma_for_radius(radius_px);
    let [nx, ny, nz] = normal;
    let slope = |a: &Plane, z: &Plane| -> Plane {
        let data = a
            .data
            .par_iter()
            .zip(&z.data)
            .map(|(&a, &z)| (-a / z.max(1e-3)).clamp(-MAX_SLOPE, MAX_SLOPE))
            .collect();
        Plane {
            width: w,
            height: h,
            data,
        }
    };
    let (mut p, mut q) = rayon::join(|| slope(nx, nz), || slope(ny, nz));
    let weight = (!solved.iter().all(|&s| s)).then(|| {
        let mask = Plane {
            width: w,
            height: h,
            data: solved.iter().map(|&s| s as u8 as f32).collect(),
        };
        for slope in [&mut p, &mut q] {
            slope
                .data
                .par_iter_mut()
                .zip(&mask.data)
                .for_each(|(v, m)| *v *= m);
        }
        gaussian_blur(&mask, sigma)
    });
    rayon::join(
        || high_pass(&mut p, sigma, weight.as_ref()),
        || high_pass(&mut q, sigma, weight.as_ref()),
    );
    nx.data
        .par_iter_mut()
        .zip(ny.data.par_iter_mut())
        .zip(nz.data.par_iter_mut())
        .zip(p.data.par_iter().zip(&q.data))
        .zip(solved)
        .for_each(|((((x, y), z), (&p, &q)), &solved)| {
            if !solved {
                return;
            }
            let inv = 1.0 / (p * p + q * q + 1.0).sqrt();
            *x = -p * inv;
            *y = -q * inv;
            *z = inv;
        });
}

/// `plane -= gaussian(plane, sigma)`, or with `weight` (the blurred mask, the plane zero
/// outside the mask) `plane -= gaussian(plane, sigma) / weight`: the low-pass of the masked
/// pixels alone. A pixel whose weight is nearly 0 (no solved pixel within reach) keeps its
/// value; outside the mask it is not used.
fn high_pass(plane: &mut Plane, sigma: f64, weight: Option<&Plane>) {
    let low = gaussian_blur(plane, sigma);
    match weight {
        None => plane
            .data
            .par_iter_mut()
            .zip(&low.data)
            .for_each(|(v, l)| *v -= l),
        Some(weight) => plane
            .data
            .par_iter_mut()
            .zip(low.data.par_iter().zip(&weight.data))
            .for_each(|(v, (l, m))| {
                if *m > 1e-6 {
                    *v -= l / m;
                }
            }),
    }
}

/// Three passes of a box of odd width `2r+1` in x and in y, with mirrored borders; the width
/// is chosen so the cascade's variance `3 ((2r+1)^2 - 1) / 12` is closest to `sigma^2`.
pub fn gaussian_blur(plane: &Plane, sigma: f64) -> Plane {
    let r = (((4.0 * sigma * sigma + 1.0).sqrt() - 1.0) / 2.0)
        .round()
        .max(0.0) as usize;
    let (w, h) = (plane.width, plane.height);
    let mut data = plane.data.clone();
    for _ in 0..3 {
        data.par_chunks_mut(w).for_each(|row| box_1d(row, r));
    }
    let mut t = transpose(&data, w, h);
    for _ in 0..3 {
        t.par_chunks_mut(h).for_each(|col| box_1d(col, r));
    }
    Plane {
        width: w,
        height: h,
        data: transpose(&t, h, w),
    }
}

/// Running-sum box filter of half-width `r` with mirrored (half-sample symmetric) ends.
fn box_1d(line: &mut [f32], r: usize) {
    let n = line.len();
    if r == 0 || n < 2 {
        return;
    }
    let at = |i: isize| -> f64 {
        let period = 2 * n as isize;
        let mut k = i.rem_euclid(period);
        if k >= n as isize {
            k = period - 1 - k;
        }
        line[k as usize] as f64
    };
    let r = r as isize;
    let mut sum: f64 = (-r..=r).map(at).sum();
    let norm = 1.0 / (2 * r + 1) as f64;
    let mut out = Vec::with_capacity(n);
    for i in 0..n as isize {
        out.push((sum * norm) as f32);
        sum += at(i + r + 1) - at(i - r);
    }
    line.copy_from_slice(&out);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::maps::derive::fft::Fft2;
    use rustfft::num_complex::Complex32;
    use std::f64::consts::TAU;

    /// A weave-like height field: short waves in x and y (periods 7 and 9 px) and a diagonal
    /// one (period 12 px), all well above the cut-off frequency of a 32 px radius.
    fn detail_slopes(x: f64, y: f64) -> (f64, f64) {
        let a = 0.35;
        let (k1, k2, k3) = (TAU / 7.0, TAU / 9.0, TAU / 12.0);
        let p = a * ((k1 * x).cos() + (k3 * (x + y)).cos());
        let q = a * ((k2 * y).cos() + (k3 * (x + y)).cos());
        (p, q)
    }

    fn normal_from_slopes(p: f64, q: f64) -> [f64; 3] {
        let inv = 1.0 / (p * p + q * q + 1.0).sqrt();
        [-p * inv, -q * inv, inv]
    }

    fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
        (a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees()
    }

    fn planes(w: usize, h: usize, f: impl Fn(f64, f64) -> [f64; 3]) -> [Plane; 3] {
        super::super::normal_field(w, h, |x, y| f(x as f64, y as f64))
    }

    /// Energy of a slope plane at spatial frequencies above `cutoff` (cycles per pixel).
    fn energy_above(plane: &[f32], w: usize, h: usize, cutoff: f64) -> f64 {
        let fft = Fft2::new(w, h);
        let spectrum = fft.forward(plane.iter().map(|&v| Complex32::new(v, 0.0)).collect());
        let mut e = 0.0;
        for u in 0..w {
            for v in 0..h {
                let fu = u.min(w - u) as f64 / w as f64;
                let fv = v.min(h - v) as f64 / h as f64;
                if (fu * fu + fv * fv).sqrt() > cutoff {
                    e += spectrum[u * h + v].norm_sqr() as f64;
                }
            }
        }
        e
    }

    #[test]
    fn injected_tilt_is_removed_and_the_detail_kept() {
        let (w, h, radius) = (512, 384, 32.0);
        // The tilt: a 6 deg plane plus a fold of 16 radii wavelength with 4 deg slope.
        let tilt = |x: f64, y: f64| {
            let plane = (6.0f64.to_radians().tan(), -2.0f64.to_radians().tan());
            let k = TAU / (16.0 * radius);
            let fold = 4.0f64.to_radians().tan() * (k * (x + 0.5 * y)).sin();
            (plane.0 + fold, plane.1 + 0.5 * fold)
        };
        let truth = planes(w, h, |x, y| {
            let (p, q) = detail_slopes(x, y);
            normal_from_slopes(p, q)
        });
        let mut tilted = planes(w, h, |x, y| {
            let (p, q) = detail_slopes(x, y);
            let (tp, tq) = tilt(x, y);
            normal_from_slopes(p + tp, q + tq)
        });
        let before = mean_angle(&tilted, &truth);
        flatten(&mut tilted, &vec![true; w * h], radius);
        let after = mean_angle(&tilted, &truth);
        assert!(before > 4.0, "the injected tilt is visible: {before} deg");
        assert!(
            after < 0.2,
            "tilt left after flattening: {after} deg (was {before})"
        );

        // Energy above the cut-off (1 / radius) of the detail's slopes, kept.
        let slope = |n: &[Plane; 3]| -> Vec<f32> {
            n[0].data
                .iter()
                .zip(&n[2].data)
                .map(|(x, z)| -x / z)
                .collect()
        };
        let cutoff = 1.0 / radius;
        let e_truth = energy_above(&slope(&truth), w, h, cutoff);
        let e_flat = energy_above(&slope(&tilted), w, h, cutoff);
        let kept = e_flat / e_truth;
        eprintln!("flatten: tilt {before:.3} deg -> {after:.4} deg mean; energy above cut-off kept {kept:.4}");
        assert!(
            (0.95..=1.05).contains(&kept),
            "energy above cut-off kept: {kept}"
        );
    }

    #[test]
    fn a_masked_object_is_flattened_from_its_own_pixels_only() {
        // The tilted detail on a disc (an object on a background); outside it the unsolved
        // pixels hold the flat normal a solve writes there.
        let (w, h, radius) = (384, 320, 32.0);
        let inside = |x: f64, y: f64| (x - 192.0).powi(2) + (y - 160.0).powi(2) < 140.0f64.powi(2);
        let solved: Vec<bool> = (0..w * h)
            .map(|i| inside((i % w) as f64, (i / w) as f64))
            .collect();
        let tilt = (8.0f64.to_radians().tan(), 5.0f64.to_radians().tan());
        let field = |x: f64, y: f64, tilted: bool| {
            if !inside(x, y) {
                return [0.0, 0.0, 1.0];
            }
            let (p, q) = detail_slopes(x, y);
            let (tp, tq) = if tilted { tilt } else { (0.0, 0.0) };
            normal_from_slopes(p + tp, q + tq)
        };
        let truth = planes(w, h, |x, y| field(x, y, false));
        let error_inside = |n: &[Plane; 3]| -> f64 {
            let picked: Vec<usize> = (0..w * h).filter(|&i| solved[i]).collect();
            let v = |p: &[Plane; 3], i: usize| [0, 1, 2].map(|c| p[c].data[i] as f64);
            picked
                .iter()
                .map(|&i| angle_deg(v(n, i), v(&truth, i)))
                .sum::<f64>()
                / picked.len() as f64
        };
        let mut masked = planes(w, h, |x, y| field(x, y, true));
        let mut unmasked = masked.clone();
        let before = error_inside(&masked);
        flatten(&mut masked, &solved, radius);
        flatten(&mut unmasked, &vec![true; w * h], radius);
        let (after, blind) = (error_inside(&masked), error_inside(&unmasked));
        eprintln!(
            "masked flatten: {before:.3} deg -> {after:.4} deg; ignoring the mask {blind:.3} deg"
        );
        assert!(after < 0.2, "tilt left inside the mask: {after} deg");
        // The background, taken as data, pulls the tilt toward zero near the edge.
        assert!(blind > 3.0 * after, "{blind} vs {after}");
        // Unsolved pixels keep their normal.
        assert!((0..w * h)
            .filter(|&i| !solved[i])
            .all(|i| masked[2].data[i] == 1.0));
    }

    fn mean_angle(a: &[Plane; 3], b: &[Plane; 3]) -> f64 {
        let n = a[0].len();
        (0..n)
            .map(|i| {
                let v = |p: &[Plane; 3]| [0, 1, 2].map(|c| p[c].data[i] as f64);
                angle_deg(v(a), v(b))
            })
            .sum::<f64>()
            / n as f64
    }

    #[test]
    fn blur_keeps_constants_and_has_the_gaussians_variance() {
        let mut p = Plane::new(101, 1, 0.0);
        p.data[50] = 1.0;
        let wide = Plane::new(101, 3, 2.5);
        let b = gaussian_blur(&wide, 5.0);
        assert!(b.data.iter().all(|v| (v - 2.5).abs() < 1e-5));
        let mut line = p.data.clone();
        for _ in 0..3 {
            box_1d(&mut line, 4);
        }
        let var: f64 = line
            .iter()
            .enumerate()
            .map(|(i, &v)| v as f64 * ((i as f64 - 50.0).powi(2)))
            .sum();
        assert!((var - 3.0 * (81.0 - 1.0) / 12.0).abs() < 1e-4, "{var}");
        assert!(kept_fraction(32.0, 1.0 / 32.0) > 0.99);
    }
}
