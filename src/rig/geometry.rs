//! Geometry of the rig: pixels to rays to points on the sample plane, world points back to
//! pixels, and what an LED delivers to a point (direction, inverse-square falloff, beam).

use nalgebra::{Matrix3, Vector3};

use super::{Camera, Led};

impl Camera {
    /// Rotation that takes camera-frame vectors (OpenCV: x right, y down, z forward) to the
    /// world frame (+x along columns, +y toward the top of the image, +z up).
    pub fn world_from_camera(&self) -> Matrix3<f64> {
        // Looking straight down: camera x = world x, camera y = world -y, camera z = world -z.
        let nadir = Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0);
        let [rx, ry, rz] = self.rotation_deg.map(f64::to_radians);
        let tilt = nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), rz)
            * nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), ry)
            * nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), rx);
        tilt.matrix() * nadir
    }

    /// The sensor's size in whole pixels of a binning `step` (partial edge bins dropped).
    pub fn binned_size(&self, step: f64) -> (usize, usize) {
        (
            (self.width as f64 / step).floor() as usize,
            (self.height as f64 / step).floor() as usize,
        )
    }

    /// The centre of projection, world metres.
    pub fn centre(&self) -> Vector3<f64> {
        Vector3::from(self.position_m)
    }

    fn has_distortion(&self) -> bool {
        self.distortion.iter().any(|&d| d != 0.0)
    }

    /// OpenCV's distortion model on normalised image coordinates.
    pub fn distort_normalized(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        (xd, yd)
    }

    /// Inverts `distort_normalized` by fixed-point iteration (what OpenCV's undistortPoints
    /// does); converges in a few steps for the mild distortion of a lens used for copy work.
    pub fn undistort_normalized(&self, xd: f64, yd: f64) -> (f64, f64) {
        if !self.has_distortion() {
            return (xd, yd);
        }
        let [k1, k2, p1, p2, k3] = self.distortion;
        let (mut x, mut y) = (xd, yd);
        for _ in 0..20 {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            let (nx, ny) = ((xd - dx) / radial, (yd - dy) / radial);
            let converged = (nx - x).abs() < 1e-14 && (ny - y).abs() < 1e-14;
            (x, y) = (nx, ny);
            if converged {
                break;
            }
        }
        (x, y)
    }

    /// World direction of the ray through sensor pixel `(u, v)` (not normalised).
    pub fn pixel_ray(&self, u: f64, v: f64) -> Vector3<f64> {
        let (x, y) = self.undistort_normalized((u - self.cx) / self.fx, (v - self.cy) / self.fy);
        self.world_from_camera() * Vector3::new(x, y, 1.0)
    }

    /// Projects a world point to sensor pixel coordinates; `None` behind the camera.
    pub fn project(&self, point: &Vector3<f64>) -> Option<(f64, f64)> {
        let in_camera = self.world_from_camera().transpose() * (point - self.centre());
        if in_camera.z <= 0.0 {
            return None;
        }
        let (xd, yd) =
            self.distort_normalized(in_camera.x / in_camera.z, in_camera.y / in_camera.z);
        Some((self.fx * xd + self.cx, self.fy * yd + self.cy))
    }

    /// A precomputed mapping from sensor pixels to points on the plane `z = plane_z`.
    pub fn plane_mapper(&self, plane_z: f64) -> PlaneMapper<'_> {
        PlaneMapper {
            camera: self,
            rotation: self.world_from_camera(),
            centre: self.centre(),
            plane_z,
        }
    }
}

/// Maps sensor pixels to the world points where their rays meet a horizontal plane.
pub struct PlaneMapper<'a> {
    camera: &'a Camera,
    rotation: Matrix3<f64>,
    centre: Vector3<f64>,
    plane_z: f64,
}

impl PlaneMapper<'_> {
    /// The point on the plane seen by sensor pixel `(u, v)`; `None` if the ray never reaches
    /// the plane (a camera tilted past the horizon).
    #[inline]
    pub fn map(&self, u: f64, v: f64) -> Option<Vector3<f64>> {
        let c = self.camera;
        let (x, y) = c.undistort_normalized((u - c.cx) / c.fx, (v - c.cy) / c.fy);
        let ray = self.rotation * Vector3::new(x, y, 1.0);
        let t = (self.plane_z - self.centre.z) / ray.z;
        (t.is_finite() && t > 0.0).then(|| self.centre + ray * t)
    }
}

/// What one LED delivers to one point: the unit direction from the point toward the LED and
/// the falloff factor `beam(theta) / r^2` (times the LED's power), so that a white Lambertian
/// surface with normal `n` reads `falloff * colour * (n . direction)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightSample {
    /// Unit vector from the point toward the LED, world frame.
    pub direction: Vector3<f64>,
    /// `power * beam(theta) / r^2`, r in metres: the linear signal a white Lambertian surface
    /// facing the LED would read there.
    pub falloff: f64,
}

impl Led {
    /// The LED's position, world metres.
    pub fn position(&self) -> Vector3<f64> {
        Vector3::from(self.position_m)
    }

    /// Unit vector along the beam, from the LED toward its aim point.
    pub fn axis(&self) -> Vector3<f64> {
        (Vector3::from(self.aim_m) - self.position()).normalize()
    }

    /// Exponent `m` of the `cos^m` beam that halves at `beam_half_angle_deg`
    /// (60 degrees gives m = 1, a Lambertian emitter).
    ///
    /// An exponent within rounding of a whole number is that number: `cos(60 deg)` rounds to
    /// `0.5000000000000001`, which made the Lambertian emitter's `m` 0.9999999999999998 and
    /// cost every near-light sample a `powf` (a twentieth of the exact kernel's time).
    pub fn beam_exponent(&self) -> f64 {
        let m = 0.5f64.ln() / self.beam_half_angle_deg.to_radians().cos().ln();
        if (m - m.round()).abs() <= 1e-12 * m {
            m.round()
        } else {
            m
        }
    }

    /// Relative intensity of the beam at angle `cos_theta` off the axis.
    #[inline]
    pub fn beam(&self, cos_theta: f64) -> f64 {
        if cos_theta <= 0.0 {
            0.0
        } else {
            cos_theta.powf(self.beam_exponent())
        }
    }

    /// Direction and falloff at a world point (near-light model: the direction and the
    /// intensity both change across the sample).
    pub fn sample_at(&self, point: &Vector3<f64>) -> LightSample {
        let to_led = self.position() - point;
        let r2 = to_led.norm_squared();
        let direction = to_led / r2.sqrt();
        let cos_theta = -self.axis().dot(&direction);
        LightSample {
            direction,
            falloff: self.power * self.beam(cos_theta) / r2,
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::rig::Rig;
    use nalgebra::Vector3;

    #[test]
    fn the_principal_point_looks_straight_down_at_the_table_centre() {
        let rig = Rig::default_rig();
        let cam = &rig.camera;
        let p = cam.plane_mapper(0.0).map(cam.cx, cam.cy).unwrap();
        assert!(p.norm() < 1e-12, "{p:?}");
        // One pixel right is +x, one pixel down is -y, each 0.6 m / fx on the table.
        let right = cam.plane_mapper(0.0).map(cam.cx + 1.0, cam.cy).unwrap();
        let down = cam.plane_mapper(0.0).map(cam.cx, cam.cy + 1.0).unwrap();
        assert!((right.x - 0.6 / cam.fx).abs() < 1e-12 && right.y.abs() < 1e-15);
        assert!((down.y + 0.6 / cam.fy).abs() < 1e-12 && down.x.abs() < 1e-15);
    }

    #[test]
    fn project_inverts_the_plane_mapping_with_distortion_and_tilt() {
        let mut rig = Rig::default_rig();
        rig.camera.distortion = [-0.12, 0.05, 0.001, -0.0005, 0.0];
        rig.camera.rotation_deg = [2.0, -1.5, 10.0];
        let cam = &rig.camera;
        let mapper = cam.plane_mapper(0.001);
        for &(u, v) in &[
            (0.0, 0.0),
            (4927.0, 3263.0),
            (1000.5, 2500.25),
            (2463.5, 1631.5),
        ] {
            let p = mapper.map(u, v).unwrap();
            assert!((p.z - 0.001).abs() < 1e-12);
            let (pu, pv) = cam.project(&p).unwrap();
            assert!(
                (pu - u).abs() < 1e-6 && (pv - v).abs() < 1e-6,
                "{u},{v} -> {pu},{pv}"
            );
        }
    }

    #[test]
    fn led_falloff_is_inverse_square_times_the_beam() {
        let rig = Rig::default_rig();
        let led = &rig.leds[6];
        assert_eq!(led.beam_exponent(), 1.0);
        let at_centre = led.sample_at(&Vector3::zeros());
        assert!((at_centre.falloff - led.power / 0.36).abs() < 1e-3 * led.power);
        assert!((at_centre.direction.norm() - 1.0).abs() < 1e-12);
        // Off axis the beam reduces the falloff beyond the inverse square.
        let p = Vector3::new(0.1, -0.1, 0.0);
        let s = led.sample_at(&p);
        let r2 = (led.position() - p).norm_squared();
        let cos_theta = -led.axis().dot(&s.direction);
        assert!(cos_theta < 1.0);
        assert!((s.falloff - led.power * cos_theta / r2).abs() < 1e-12);
    }
}
