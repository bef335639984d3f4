//! Height from the normal map by Frankot-Chellappa: the least-squares integrable surface for
//! the slopes, solved in the Fourier domain. A sample's edges are not periodic, so the slopes
//! are mirrored to twice the size first (an even extension of the height, which has no jump
//! at the wrap); a tile that already repeats is integrated as it is.

use rayon::prelude::*;
use rustfft::num_complex::Complex32;

use super::fft::{angular_frequency, Fft2};
use crate::plane::Plane;

/// Slopes steeper than this (63 deg) are clamped: a woven sample's steps (thread edge down to
/// the gap) have no normal a camera can measure, and the near-horizontal normals sampled on
/// them are not integrable; left unclamped they bend the whole height field.
const MAX_SLOPE: f32 = 2.0;

/// Whether the map's edges meet (a seamless tile) or not (a scanned sample).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Boundary {
    Periodic,
    Mirrored,
}

/// Integrates the unit normal map (world frame: +y toward the top of the image) into a height
/// field with zero mean, in units of `pixel_size` (height in mm for a size in mm).
pub fn integrate(normal: &[Plane; 3], pixel_size: f64, boundary: Boundary) -> Plane {
    let (w, h) = (normal[0].width, normal[0].height);
    // dz/dx along columns, dz/drow along rows (rows run toward -y).
    let slope = |i: usize| -> (f32, f32) {
        let z = normal[2].data[i].max(1e-3);
        let p = (-normal[0].data[i] / z).clamp(-MAX_SLOPE, MAX_SLOPE);
        let q = (normal[1].data[i] / z).clamp(-MAX_SLOPE, MAX_SLOPE);
        (p, q)
    };
    let (ew, eh) = match boundary {
        Boundary::Periodic => (w, h),
        Boundary::Mirrored => (2 * w, 2 * h),
    };
    // p + i q in one complex buffer: both are real, so one transform carries both.
    let mut buf = vec![Complex32::default(); ew * eh];
    buf.par_chunks_mut(ew).enumerate().for_each(|(ey, row)| {
        let (y, flip_y) = fold(ey, h);
        for (ex, v) in row.iter_mut().enumerate() {
            let (x, flip_x) = fold(ex, w);
            let (mut p, mut q) = slope(y * w + x);
            // Mirroring the height negates the slope across the mirror's axis.
            if flip_x {
                p = -p;
            }
            if flip_y {
                q = -q;
            }
            *v = Complex32::new(p, q);
        }
    });
    let fft = Fft2::new(ew, eh);
    let mut spectrum = fft.forward(buf);
    // Transposed layout: index u * eh + v. P(k) = (G(k) + G*(-k)) / 2, Q = (G - G*(-k)) / 2i.
    let g = spectrum.clone();
    spectrum
        .par_chunks_mut(eh)
        .enumerate()
        .for_each(|(u, column)| {
            let wu = angular_frequency(u, ew);
            let mu = (ew - u) % ew;
            for (v, out) in column.iter_mut().enumerate() {
                let wv = angular_frequency(v, eh);
                let mv = (eh - v) % eh;
                let d = wu * wu + wv * wv;
                if d == 0.0 {
                    *out = Complex32::default();
                    continue;
                }
                let gk = g[u * eh + v];
                let gm = g[mu * eh + mv].conj();
                let p = (gk + gm) * 0.5;
                let q = (gk - gm) * Complex32::new(0.0, -0.5);
                // z = F^-1[ -i (wu P + wv Q) / (wu^2 + wv^2) ]
                *out = (p * wu + q * wv) * Complex32::new(0.0, -1.0 / d);
            }
        });
    drop(g);
    let z = fft.inverse(spectrum);
    let scale = pixel_size as f32;
    let mut data = vec![0.0f32; w * h];
    data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, v) in row.iter_mut().enumerate() {
            *v = z[y * ew + x].re * scale;
        }
    });
    let mean = data.iter().map(|&v| v as f64).sum::<f64>() / data.len() as f64;
    data.par_iter_mut().for_each(|v| *v -= mean as f32);
    Plane {
        width: w,
        height: h,
        data,
    }
}

/// Index into the original of position `e` of the mirrored extension, and whether it is in
/// the mirrored half.
fn fold(e: usize, n: usize) -> (usize, bool) {
    if e < n {
        (e, false)
    } else {
        (2 * n - 1 - e, true)
    }
}

/// RMS of `a - b` after removing the best-fitting plane `c0 + c1 x + c2 y` of the difference
/// (the offset and tilt integration cannot see); the figure the height tests report.
pub fn rms_after_plane(a: &Plane, b: &Plane) -> f64 {
    let (w, h) = (a.width, a.height);
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = nalgebra::Vector3::<f64>::zeros();
    for y in 0..h {
        for x in 0..w {
            let r = nalgebra::Vector3::new(1.0, x as f64, y as f64);
            let d = (a.data[y * w + x] - b.data[y * w + x]) as f64;
            ata += r * r.transpose();
            atb += r * d;
        }
    }
    let c = ata.lu().solve(&atb).unwrap_or_default();
    let mut sum = 0.0;
    for y in 0..h {
        for x in 0..w {
            let d = (a.data[y * w + x] - b.data[y * w + x]) as f64;
            let e = d - (c[0] + c[1] * x as f64 + c[2] * y as f64);
            sum += e * e;
        }
    }
    (sum / (w * h) as f64).sqrt()
}

/// Range (max - min) of a plane.
pub fn range(p: &Plane) -> f64 {
    let (lo, hi) = p
        .data
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    (hi - lo) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::textile::Textile;

    /// The synthetic textile sampled on a grid of `px_m` metres: its true height (mm) and its
    /// true normals (world frame, +y toward the top of the image, so row `r` is at -y).
    fn textile_grid(w: usize, h: usize, px_m: f64) -> (Plane, [Plane; 3]) {
        let t = Textile::default();
        let mut height = Plane::new(w, h, 0.0);
        let mut n = [
            Plane::new(w, h, 0.0),
            Plane::new(w, h, 0.0),
            Plane::new(w, h, 0.0),
        ];
        for r in 0..h {
            for c in 0..w {
                let (x, y) = (
                    (c as f64 - w as f64 / 2.0) * px_m,
                    -(r as f64 - h as f64 / 2.0) * px_m,
                );
                let i = r * w + c;
                height.data[i] = (t.height_at(x, y) * 1e3) as f32;
                let v = t.normal_at(x, y);
                for k in 0..3 {
                    n[k].data[i] = v[k] as f32;
                }
            }
        }
        (height, n)
    }

    #[test]
    fn true_normals_of_the_synthetic_textile_integrate_to_its_height() {
        // 0.05 mm pixels: 18 px per thread, a 25.6 x 19.2 mm window over part of a fold.
        let (w, h, px_mm) = (512, 384, 0.05);
        let (truth, normals) = textile_grid(w, h, px_mm * 1e-3);
        let z = integrate(&normals, px_mm, Boundary::Mirrored);
        let rms = rms_after_plane(&z, &truth);
        let range = range(&truth);
        eprintln!(
            "height from true normals: RMS {rms:.4} mm of range {range:.3} mm = {:.2} %",
            100.0 * rms / range
        );
        assert!(rms < 0.05 * range, "RMS {rms} mm vs range {range} mm");
    }

    #[test]
    fn a_smooth_periodic_surface_is_recovered_exactly() {
        // z = sin(2 pi x / 32) cos(2 pi y / 16) on a 64 x 48 periodic grid, slopes analytic.
        let (w, h) = (64, 48);
        let (kx, ky) = (std::f64::consts::TAU / 32.0, std::f64::consts::TAU / 16.0);
        let mut truth = Plane::new(w, h, 0.0);
        let mut n = [
            Plane::new(w, h, 0.0),
            Plane::new(w, h, 0.0),
            Plane::new(w, h, 0.0),
        ];
        for r in 0..h {
            for c in 0..w {
                let (x, y) = (c as f64, -(r as f64));
                let z = (kx * x).sin() * (ky * y).cos();
                let (p, q) = (
                    kx * (kx * x).cos() * (ky * y).cos(),
                    -ky * (kx * x).sin() * (ky * y).sin(),
                );
                let inv = 1.0 / (p * p + q * q + 1.0).sqrt();
                let i = r * w + c;
                truth.data[i] = z as f32;
                n[0].data[i] = (-p * inv) as f32;
                n[1].data[i] = (-q * inv) as f32;
                n[2].data[i] = inv as f32;
            }
        }
        let z = integrate(&n, 1.0, Boundary::Periodic);
        let rms = rms_after_plane(&z, &truth);
        assert!(rms < 1e-4, "{rms}");
        let z = integrate(&n, 1.0, Boundary::Mirrored);
        assert!(
            rms_after_plane(&z, &truth) < 0.02,
            "{}",
            rms_after_plane(&z, &truth)
        );
    }
}
