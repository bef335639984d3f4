//! The camera's own colour matrix, for outputs that need display colour.
//!
//! psscan solves in the camera's white-balanced RGB (each channel divided by the lights'
//! colour, so a white surface has albedo (a, a, a)). That is right for the normal map and for
//! linear albedo data, but a display needs sRGB primaries. A RAW file's colour matrix maps CIE
//! XYZ to camera RGB; with sRGB's primaries it gives camera RGB from linear sRGB, which is
//! normalised so that sRGB white maps to camera white (rows summing to one, the way dcraw
//! builds its `rgb_cam`) and inverted.

use nalgebra::Matrix3;

/// Linear sRGB (D65) to CIE XYZ (IEC 61966-2-1).
const SRGB_TO_XYZ: [[f64; 3]; 3] = [
    [0.412_456_4, 0.357_576_1, 0.180_437_5],
    [0.212_672_9, 0.715_152_2, 0.072_175_0],
    [0.019_333_9, 0.119_192_0, 0.950_304_1],
];

/// White-balanced camera RGB to linear sRGB, from a RAW file's XYZ-to-camera matrix (row
/// major, one row per camera colour R, G, B). `None` when the matrix is not 3x3 or cannot be
/// inverted (then outputs stay in camera RGB, and the report says so).
pub fn camera_to_srgb(xyz_to_camera: &[f32]) -> Option<[[f64; 3]; 3]> {
    if xyz_to_camera.len() != 9 || xyz_to_camera.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let xyz_to_cam = Matrix3::from_row_iterator(xyz_to_camera.iter().map(|&v| v as f64));
    let srgb_to_xyz = Matrix3::from_row_iterator(SRGB_TO_XYZ.iter().flatten().copied());
    let mut srgb_to_cam = xyz_to_cam * srgb_to_xyz;
    for mut row in srgb_to_cam.row_iter_mut() {
        let sum: f64 = row.iter().sum();
        if sum.abs() < 1e-9 {
            return None;
        }
        row /= sum;
    }
    let cam_to_srgb = srgb_to_cam.try_inverse()?;
    if cam_to_srgb.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let mut out = [[0.0; 3]; 3];
    for (r, row) in out.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = cam_to_srgb[(r, c)];
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// XYZ to linear sRGB: the inverse of `SRGB_TO_XYZ` (what the synthetic DNGs carry).
    fn xyz_to_srgb() -> Vec<f32> {
        let m = Matrix3::from_row_iterator(SRGB_TO_XYZ.iter().flatten().copied());
        let inv = m.try_inverse().unwrap();
        (0..9).map(|i| inv[(i / 3, i % 3)] as f32).collect()
    }

    #[test]
    fn a_camera_with_srgb_primaries_needs_no_conversion() {
        let m = camera_to_srgb(&xyz_to_srgb()).unwrap();
        for (r, row) in m.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                let want = if r == c { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 1e-5, "{m:?}");
            }
        }
    }

    #[test]
    fn camera_white_stays_white_and_bad_matrices_are_refused() {
        // Canon EOS 550D's D65 XYZ-to-camera matrix (as in Adobe's DNG converter and dcraw).
        let canon = [
            0.6941, -0.1164, -0.0857, -0.3825, 1.1597, 0.2534, -0.0416, 0.1540, 0.6039,
        ];
        let m = camera_to_srgb(&canon).unwrap();
        for row in m {
            let sum: f64 = row.iter().sum();
            assert!((sum - 1.0).abs() < 1e-9, "white must map to white: {m:?}");
        }
        // A real camera's primaries are not sRGB's: the matrix must do something.
        assert!(m[0][0] > 1.2 && m[0][1] < 0.0, "{m:?}");
        assert_eq!(camera_to_srgb(&canon[..8]), None);
        assert_eq!(camera_to_srgb(&[0.0; 9]), None);
        assert_eq!(camera_to_srgb(&[f32::NAN; 9]), None);
    }
}
