//! The trimmed least-squares anchor: per pixel, drop the darkest and the brightest fifth of the
//! readings and fit a Lambertian normal to the rest. A rule anyone can reproduce in a few lines,
//! so a robust estimator that does not beat it has no claim on real data.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::plane::{Frames, Mask};
use crate::solve::LUMINANCE_WEIGHTS;

/// Fraction of the readings dropped at each end.
pub const TRIM_FRACTION: f64 = 0.2;

/// How many readings of `lights` the trimmed rule drops at each end: 20 % rounded, so 2 of 10,
/// 4 of 20, 19 of 96, never so many that fewer than 3 remain.
pub fn trimmed_per_end(lights: usize) -> usize {
    let t = (TRIM_FRACTION * lights as f64).round() as usize;
    t.min(lights.saturating_sub(3) / 2)
}

/// Trimmed least-squares normals of every `mask` pixel (luminance over light intensity, as the
/// solver reads it); `None` outside the mask or where the kept lights are degenerate.
pub fn trimmed_normals(
    frames: &Frames,
    directions: &[[f64; 3]],
    intensities: &[[f64; 3]],
    mask: Option<&Mask>,
) -> Vec<Option<Vector3<f64>>> {
    let n = frames.width * frames.height;
    let lights: Vec<Vector3<f64>> = directions
        .iter()
        .map(|d| Vector3::new(d[0], d[1], d[2]).normalize())
        .collect();
    let drop = trimmed_per_end(lights.len());
    (0..n)
        .into_par_iter()
        .map_init(Vec::new, |readings: &mut Vec<(f64, usize)>, i| {
            if mask.is_some_and(|m| !m.data[i]) {
                return None;
            }
            readings.clear();
            let (x, y) = (i % frames.width, i / frames.width);
            for (k, frame) in frames.lights.iter().enumerate() {
                let rgb = frame.rgb_at(x, y);
                let lum: f64 = (0..3)
                    .map(|c| LUMINANCE_WEIGHTS[c] * rgb[c] as f64 / intensities[k][c])
                    .sum();
                readings.push((lum, k));
            }
            readings.sort_by(|a, b| a.0.total_cmp(&b.0));
            let kept = &readings[drop..readings.len() - drop];
            let mut a = Matrix3::zeros();
            let mut b = Vector3::zeros();
            for &(lum, k) in kept {
                a += lights[k] * lights[k].transpose();
                b += lights[k] * lum;
            }
            a.try_inverse()
                .map(|inv| inv * b)
                .and_then(|g| g.try_normalize(1e-12))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plane::{LightFrame, RgbPlanes, SensorWindow};

    #[test]
    fn ends_dropped_by_count() {
        assert_eq!(trimmed_per_end(10), 2);
        assert_eq!(trimmed_per_end(20), 4);
        assert_eq!(trimmed_per_end(96), 19);
        assert_eq!(trimmed_per_end(4), 0);
    }

    #[test]
    fn trimming_removes_a_shadow_and_a_highlight() {
        // One pixel, ten lights, Lambertian with one reading zeroed (shadow) and one doubled
        // (highlight): the trimmed fit recovers the normal exactly.
        let normal = Vector3::new(0.3, -0.2, 0.9).normalize();
        let dirs: Vec<[f64; 3]> = (0..10)
            .map(|j| {
                let a = j as f64 * 0.628;
                let v = Vector3::new(a.cos() * 0.5, a.sin() * 0.5, 0.85).normalize();
                [v.x, v.y, v.z]
            })
            .collect();
        let frames = Frames {
            width: 1,
            height: 1,
            window: SensorWindow::FULL,
            lights: dirs
                .iter()
                .enumerate()
                .map(|(k, d)| {
                    let mut v = 0.5 * normal.dot(&Vector3::new(d[0], d[1], d[2]));
                    v *= [1.0, 0.0, 1.0, 1.0, 2.0, 1.0, 1.0, 1.0, 1.0, 1.0][k];
                    let mut rgb = RgbPlanes::new(1, 1);
                    for plane in [&mut rgb.r, &mut rgb.g, &mut rgb.b] {
                        plane.data[0] = v as f32;
                    }
                    LightFrame {
                        rgb,
                        saturated: None,
                        cfa: None,
                        dn: None,
                        cfa_dn: None,
                    }
                })
                .collect(),
        };
        let n = trimmed_normals(&frames, &dirs, &[[1.0; 3]; 10], None)[0].unwrap();
        assert!((n - normal).norm() < 1e-5, "{n} vs {normal}");
    }
}
