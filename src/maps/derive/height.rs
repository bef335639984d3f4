//! Height from the normal map by Frankot-Chellappa: the least-squares integrable surface for
//! the slopes, solved in the Fourier domain. A sample's edges are not periodic, so the height
//! is taken as mirrored to twice the size (an even extension, which has no jump at the wrap),
//! solved with cosine and sine transforms on the sample's own grid; a tile that already
//! repeats is integrated with the FFT as it is.

use std::sync::Arc;

use rayon::prelude::*;
use rustdct::{DctPlanner, TransformType2And3};
use rustfft::num_complex::Complex32;

use super::fft::{angular_frequency, transpose, Fft2};
use super::poisson::{self, MaskedSolve};
use crate::plane::Plane;

/// Slopes steeper than this (63 deg) are clamped: a woven sample's steps (thread edge down to
/// the gap) have no normal a camera can measure, and the near-horizontal normals sampled on
/// them are not integrable; left unclamped they bend the whole height field.
const MAX_SLOPE: f32 = 2.0;

/// Whether the map's edges meet (a seamless tile) or not (a scanned sample).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Boundary {
    /// The map is a seamless tile: integrated with the FFT as it is, opposite edges meeting.
    Periodic,
    /// The map is a scanned sample with free edges: integrated as if mirrored to twice its size, so
    /// the wrap has no jump.
    Mirrored,
}

/// Integrates the unit normal map (world frame: +y toward the top of the image) into a height
/// field with zero mean, in units of `pixel_size` (height in mm for a size in mm).
pub fn integrate(normal: &[Plane; 3], pixel_size: f64, boundary: Boundary) -> Plane {
    let (w, h) = (normal[0].width, normal[0].height);
    let (p, q) = slopes(normal);
    let z = match boundary {
        Boundary::Periodic => integrate_periodic(&p, &q, w, h),
        Boundary::Mirrored => integrate_mirrored(p, q, w, h),
    };
    let scale = pixel_size as f32;
    let mut data = z;
    let mean = data.iter().map(|&v| v as f64).sum::<f64>() / data.len() as f64;
    data.par_iter_mut()
        .for_each(|v| *v = (*v - mean as f32) * scale);
    Plane {
        width: w,
        height: h,
        data,
    }
}

/// [`integrate`] over the `solved` pixels only (one flag per pixel): where some are not
/// solved, the Fourier surface (their slopes taken as 0) is refined into the masked
/// least-squares surface ([`poisson::refine`]), and the unsolved pixels hold height 0.
/// Returns how that refinement ended; `None` when every pixel was solved.
pub fn integrate_over(
    normal: &[Plane; 3],
    solved: &[bool],
    pixel_size: f64,
    boundary: Boundary,
) -> (Plane, Option<MaskedSolve>) {
    if solved.iter().all(|&s| s) {
        return (integrate(normal, pixel_size, boundary), None);
    }
    let (w, h) = (normal[0].width, normal[0].height);
    let (p, q) = slopes(normal);
    // The starting surface: unsolved pixels take their solved neighbours' mean slope (0 with
    // none), so a hole in a scan starts out bridged by its surroundings and only the links
    // it removes are left to iterate; a background far from the object starts flat.
    let (p, q) = (
        fill_unsolved(&p, solved, w, h),
        fill_unsolved(&q, solved, w, h),
    );
    let wrap = boundary == Boundary::Periodic;
    let mut z = match boundary {
        Boundary::Periodic => integrate_periodic(&p, &q, w, h),
        Boundary::Mirrored => integrate_mirrored(p.clone(), q.clone(), w, h),
    };
    let limits = (max_iterations(w, h), poisson::TOLERANCE);
    let stats = poisson::refine(&mut z, (&p, &q), solved, (w, h), wrap, limits);
    let scale = pixel_size as f32;
    z.par_iter_mut().for_each(|v| *v *= scale);
    let plane = Plane {
        width: w,
        height: h,
        data: z,
    };
    (plane, Some(stats))
}

/// `slope` with each unsolved pixel replaced by the mean over its solved 4-neighbours (0
/// where it has none); the refinement never reads an unsolved pixel's slope.
fn fill_unsolved(slope: &[f32], solved: &[bool], w: usize, h: usize) -> Vec<f32> {
    (0..slope.len())
        .into_par_iter()
        .map(|i| {
            if solved[i] {
                return slope[i];
            }
            let (x, y) = (i % w, i / w);
            let around = [
                (x > 0).then(|| i - 1),
                (x + 1 < w).then(|| i + 1),
                (y > 0).then(|| i - w),
                (y + 1 < h).then(|| i + w),
            ];
            let (sum, count) = around
                .into_iter()
                .flatten()
                .filter(|&j| solved[j])
                .fold((0.0f32, 0u32), |(s, n), j| (s + slope[j], n + 1));
            if count > 0 {
                sum / count as f32
            } else {
                0.0
            }
        })
        .collect()
}

/// Iterations allowed to the masked refinement: preconditioned conjugate gradients on a
/// grid Laplacian settle its smoothest error (a bend across the whole mask) in a number of
/// steps proportional to the grid's side, so a few sides' worth.
fn max_iterations(w: usize, h: usize) -> usize {
    2 * (w + h) + 100
}

/// dz/dx along columns and dz/drow along rows (rows run toward -y), clamped to `MAX_SLOPE`.
fn slopes(normal: &[Plane; 3]) -> (Vec<f32>, Vec<f32>) {
    (0..normal[0].data.len())
        .into_par_iter()
        .map(|i| {
            let z = normal[2].data[i].max(1e-3);
            let p = (-normal[0].data[i] / z).clamp(-MAX_SLOPE, MAX_SLOPE);
            let q = (normal[1].data[i] / z).clamp(-MAX_SLOPE, MAX_SLOPE);
            (p, q)
        })
        .unzip()
}

/// Frankot-Chellappa on a tile whose edges meet: one complex FFT carries both slopes.
fn integrate_periodic(p: &[f32], q: &[f32], w: usize, h: usize) -> Vec<f32> {
    // p + i q in one complex buffer: both are real, so one transform carries both.
    let buf: Vec<Complex32> = p
        .par_iter()
        .zip(q)
        .map(|(&p, &q)| Complex32::new(p, q))
        .collect();
    let fft = Fft2::new(w, h);
    let g = fft.forward(buf);
    // Transposed layout: index u * h + v. P(k) = (G(k) + G*(-k)) / 2, Q = (G - G*(-k)) / 2i.
    let mut spectrum = vec![Complex32::default(); w * h];
    spectrum
        .par_chunks_mut(h)
        .enumerate()
        .for_each(|(u, column)| {
            let wu = angular_frequency(u, w);
            let mu = (w - u) % w;
            for (v, out) in column.iter_mut().enumerate() {
                let wv = angular_frequency(v, h);
                let mv = (h - v) % h;
                let d = wu * wu + wv * wv;
                if d == 0.0 {
                    continue;
                }
                let gk = g[u * h + v];
                let gm = g[mu * h + mv].conj();
                let p = (gk + gm) * 0.5;
                let q = (gk - gm) * Complex32::new(0.0, -0.5);
                // z = F^-1[ -i (wu P + wv Q) / (wu^2 + wv^2) ]
                *out = (p * wu + q * wv) * Complex32::new(0.0, -1.0 / d);
            }
        });
    drop(g);
    fft.inverse(spectrum).into_iter().map(|c| c.re).collect()
}

/// Frankot-Chellappa on the sample mirrored to twice its size, computed without building the
/// mirror: the mirrored height is even about the half-sample edges, so its spectrum is the
/// DCT-II of the height, and the mirrored slopes (odd across their own axis) have the DST-II
/// there. With w_u = pi u / W, the Fourier solution becomes, per (u, v),
///     C[z] = -(w_u S_x C_y[p] + w_v C_x S_y[q]) / (w_u^2 + w_v^2),
/// on a W x H real grid instead of a 2W x 2H complex one. The Nyquist bins (u = W or v = H),
/// where the derivative of a half-sample-even height vanishes, are left out.
fn integrate_mirrored(mut p: Vec<f32>, mut q: Vec<f32>, w: usize, h: usize) -> Vec<f32> {
    let mut planner = DctPlanner::new();
    let (along_x, along_y) = (planner.plan_dct2(w), planner.plan_dct2(h));
    // Along x (rows of length w): sine transform of p, cosine transform of q.
    rows(&mut p, w, |row, s| sine(&along_x, row, s), &along_x);
    rows(
        &mut q,
        w,
        |row, s| along_x.process_dct2_with_scratch(row, s),
        &along_x,
    );
    // Along y, on the transposed planes (index u * h + v).
    let mut sp = transpose(&p, w, h);
    let mut cq = transpose(&q, w, h);
    drop((p, q));
    rows(
        &mut sp,
        h,
        |row, s| along_y.process_dct2_with_scratch(row, s),
        &along_y,
    );
    rows(&mut cq, h, |row, s| sine(&along_y, row, s), &along_y);
    // The height's cosine spectrum, in place of sp.
    sp.par_chunks_mut(h)
        .zip(cq.par_chunks(h))
        .enumerate()
        .for_each(|(u, (column, cq))| {
            let wu = std::f32::consts::PI * u as f32 / w as f32;
            for (v, (c, &cq)) in column.iter_mut().zip(cq).enumerate() {
                let wv = std::f32::consts::PI * v as f32 / h as f32;
                let d = wu * wu + wv * wv;
                *c = if d == 0.0 {
                    0.0
                } else {
                    -(wu * *c + wv * cq) / d
                };
            }
        });
    drop(cq);
    // Back: DCT-III along y, transpose, DCT-III along x, and DCT-III * 2/N inverts DCT-II.
    rows(
        &mut sp,
        h,
        |row, s| along_y.process_dct3_with_scratch(row, s),
        &along_y,
    );
    let mut z = transpose(&sp, h, w);
    drop(sp);
    rows(
        &mut z,
        w,
        |row, s| along_x.process_dct3_with_scratch(row, s),
        &along_x,
    );
    let norm = 4.0 / (w * h) as f32;
    z.par_iter_mut().for_each(|v| *v *= norm);
    z
}

/// The sine spectrum S(k) = sum_n x[n] sin(pi k (n + 1/2) / N) at k = 0..N-1 (S(0) = 0): the
/// DST-II gives k = 1..N, shifted up one bin, and its last bin (the Nyquist) is dropped.
fn sine(transform: &Arc<dyn TransformType2And3<f32>>, row: &mut [f32], scratch: &mut [f32]) {
    transform.process_dst2_with_scratch(row, scratch);
    row.copy_within(0..row.len() - 1, 1);
    row[0] = 0.0;
}

/// Applies `f` to every `len`-long row of `data` in parallel, each worker with its scratch.
fn rows(
    data: &mut [f32],
    len: usize,
    f: impl Fn(&mut [f32], &mut [f32]) + Sync,
    transform: &Arc<dyn TransformType2And3<f32>>,
) {
    let scratch_len = transform.get_scratch_len();
    data.par_chunks_mut(len)
        .for_each_init(|| vec![0.0f32; scratch_len], |scratch, row| f(row, scratch));
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

    /// A sphere of `radius` px seen from above, centred on a `w x h` grid and solved within
    /// `rim` px of its centre; the background is unsolved (flat normal). Returns the mask,
    /// the true height (0 outside) and the normals.
    fn masked_sphere(
        w: usize,
        h: usize,
        radius: f64,
        rim: f64,
    ) -> (Vec<bool>, Vec<f64>, [Plane; 3]) {
        let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
        let mut solved = vec![false; w * h];
        let mut truth = vec![0.0f64; w * h];
        let mut n = [
            Plane::new(w, h, 0.0),
            Plane::new(w, h, 0.0),
            Plane::new(w, h, 1.0),
        ];
        for i in 0..w * h {
            let (dx, dy) = ((i % w) as f64 - cx, (i / w) as f64 - cy);
            let rho2 = dx * dx + dy * dy;
            if rho2 < rim * rim {
                solved[i] = true;
                let z = (radius * radius - rho2).sqrt();
                truth[i] = z;
                // Normal (dx, -dy, z) / radius: +y toward the top of the image (row - 1).
                n[0].data[i] = (dx / radius) as f32;
                n[1].data[i] = (-dy / radius) as f32;
                n[2].data[i] = (z / radius) as f32;
            }
        }
        (solved, truth, n)
    }

    #[test]
    fn a_sphere_on_a_background_is_recovered_over_its_mask() {
        // A sphere of radius 110 px solved within 98 px of its centre (slopes up to
        // 98 / 50 = 1.96, just below the clamp, as an object's silhouette reaches).
        let (w, h, radius, rim) = (400usize, 380usize, 110.0f64, 98.0f64);
        let (solved, truth, n) = masked_sphere(w, h, radius, rim);
        let rms_inside = |z: &Plane| -> f64 {
            let picked: Vec<usize> = (0..w * h).filter(|&i| solved[i]).collect();
            let count = picked.len() as f64;
            let offset = picked
                .iter()
                .map(|&i| z.data[i] as f64 - truth[i])
                .sum::<f64>()
                / count;
            (picked
                .iter()
                .map(|&i| (z.data[i] as f64 - truth[i] - offset).powi(2))
                .sum::<f64>()
                / count)
                .sqrt()
        };
        let (z, masked) = integrate_over(&n, &solved, 1.0, Boundary::Mirrored);
        let masked = masked.expect("a masked solve");
        let rms = rms_inside(&z);
        let plain = rms_inside(&integrate(&n, 1.0, Boundary::Mirrored));
        // The sphere's height range over the mask: 110 - sqrt(110^2 - 98^2) = 60.0 px.
        let range = radius - (radius * radius - rim * rim).sqrt();
        eprintln!(
            "sphere over its mask: RMS {rms:.4} px ({:.2} % of range) in {} iterations, \
             residual {:.1e}; Fourier alone {plain:.3} px",
            100.0 * rms / range,
            masked.iterations,
            masked.relative_residual
        );
        assert!(masked.relative_residual <= 1e-4, "{masked:?}");
        assert!(rms < 0.01 * range, "RMS {rms} px of {range}");
        assert!(plain > 5.0 * rms, "the Fourier solve alone: {plain} px");
        assert!((0..w * h).filter(|&i| !solved[i]).all(|i| z.data[i] == 0.0));
    }

    #[test]
    fn a_masked_object_with_a_steep_silhouette_stops_near_the_converged_surface() {
        // An object's silhouette: a sphere solved out to 108 of its 110 px radius, where the
        // slopes (up to 5) are clamped to 2, so they are no longer integrable. The iteration
        // stops on the residual, which says little about the smoothest error modes; this
        // checks that the stop is close to the surface the iteration converges to.
        let (w, h, radius, rim) = (360usize, 340usize, 110.0f64, 108.0f64);
        let (solved, _, n) = masked_sphere(w, h, radius, rim);
        let (z, masked) = integrate_over(&n, &solved, 1.0, Boundary::Mirrored);
        // The converged surface of the same problem: from zero, to a residual 10^6 smaller.
        let (p, q) = slopes(&n);
        let mut converged = vec![0.0f32; w * h];
        let reached = poisson::refine(
            &mut converged,
            (&p, &q),
            &solved,
            (w, h),
            false,
            (200 * (w + h), 1e-10),
        );
        assert!(reached.relative_residual <= 1e-10, "{reached:?}");
        let picked: Vec<usize> = (0..w * h).filter(|&i| solved[i]).collect();
        let range = picked
            .iter()
            .map(|&i| converged[i])
            .fold(f32::MIN, f32::max)
            - picked
                .iter()
                .map(|&i| converged[i])
                .fold(f32::MAX, f32::min);
        let rms = (picked
            .iter()
            .map(|&i| ((z.data[i] - converged[i]) as f64).powi(2))
            .sum::<f64>()
            / picked.len() as f64)
            .sqrt();
        eprintln!(
            "steep silhouette: RMS {rms:.4} px from the converged surface (range {range:.1} px), \
             {} iterations",
            masked.unwrap().iterations
        );
        assert!(rms < 1e-3 * range as f64, "RMS {rms} px of {range}");
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

    #[test]
    fn a_surface_flat_at_its_edges_is_recovered_exactly_without_periodicity() {
        // z = cos(3 pi (c + 1/2) / w) cos(2 pi (r + 1/2) / h) + 0.5 cos(5 pi (c + 1/2) / w):
        // half-sample even at every edge (what the mirrored solver assumes) but not periodic
        // on the w x h grid; its slopes are analytic, so the only error is f32 rounding.
        let (w, h) = (60, 44);
        let pi = std::f64::consts::PI;
        let (a, b, c) = (
            3.0 * pi / w as f64,
            2.0 * pi / h as f64,
            5.0 * pi / w as f64,
        );
        let mut truth = Plane::new(w, h, 0.0);
        let mut n = [
            Plane::new(w, h, 0.0),
            Plane::new(w, h, 0.0),
            Plane::new(w, h, 0.0),
        ];
        for r in 0..h {
            for col in 0..w {
                let (x, y) = (col as f64 + 0.5, r as f64 + 0.5);
                let z = (a * x).cos() * (b * y).cos() + 0.5 * (c * x).cos();
                // p = dz/dcol; q = dz/drow, which the normal carries as +n_y / n_z.
                let p = -a * (a * x).sin() * (b * y).cos() - 0.5 * c * (c * x).sin();
                let q = -b * (a * x).cos() * (b * y).sin();
                let inv = 1.0 / (p * p + q * q + 1.0).sqrt();
                let i = r * w + col;
                truth.data[i] = z as f32;
                n[0].data[i] = (-p * inv) as f32;
                n[1].data[i] = (q * inv) as f32;
                n[2].data[i] = inv as f32;
            }
        }
        let z = integrate(&n, 1.0, Boundary::Mirrored);
        let rms = rms_after_plane(&z, &truth);
        assert!(rms < 1e-4, "{rms}");
    }
}
