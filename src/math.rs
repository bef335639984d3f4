//! Small vector math shared by the solve and its evaluation (layer 0: imports nothing of the
//! crate), so that neither has to reach into the other for it.

use nalgebra::Vector3;

/// Angle between two vectors in degrees, accurate for tiny angles (atan2 of cross and dot:
/// `acos` of the dot product loses all precision below about 1e-4 degrees).
pub fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b)).to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angle_is_exact_for_tiny_and_right_angles() {
        let a = Vector3::new(0.0, 0.0, 1.0);
        let t = 1e-7f64;
        let b = Vector3::new(t.sin(), 0.0, t.cos());
        assert!((angle_deg(&a, &b) - t.to_degrees()).abs() < 1e-15);
        assert!((angle_deg(&a, &Vector3::x()) - 90.0).abs() < 1e-12);
        // Scale does not matter: the angle is between directions.
        assert!((angle_deg(&(a * 3.0), &(b * 0.5)) - t.to_degrees()).abs() < 1e-15);
    }
}
