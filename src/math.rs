//! Small vector math shared by the solve and its evaluation, and order statistics of many
//! values ([`select`]) for the evaluation and the maps (layer 0: imports nothing of the
//! crate), so that none has to reach into another for it.

pub mod select;

use nalgebra::Vector3;

/// Consistency factor of the median absolute deviation for a normal distribution: this many
/// MADs are one standard deviation of Gaussian noise, a scale that under half of the values
/// being outliers does not move.
pub const MAD_TO_SIGMA: f64 = 1.4826;

/// Angle between two vectors in degrees, accurate for tiny angles (atan2 of cross and dot:
/// `acos` of the dot product loses all precision below about 1e-4 degrees).
pub fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b)).to_degrees()
}

/// `x.round()` (half away from zero) for `0 <= x < 2^31`, and 0 for NaN, as the standard
/// library's `round` then an `as` cast to an unsigned integer give. Without target features
/// beyond SSE2 `round` (and `trunc`) is a libm call per value; the integer conversion here is
/// one instruction and vectorises, which matters where every sample of a 16 MP map is
/// quantised. The fraction `x - trunc(x)` is exact in this range, so ties go up as `round`'s
/// do (adding a half before truncating does not: the float just below 0.5 plus 0.5 is 1).
#[inline(always)]
pub fn round_non_negative(x: f32) -> f32 {
    // Truncation toward zero; NaN converts to 0 and then fails the comparison.
    let whole = (x as i32) as f32;
    whole + if x - whole >= 0.5 { 1.0 } else { 0.0 }
}

/// `exp(-e)` in single precision for `e` in `[0, 87]`, branch-free so that a loop of it
/// vectorises (the standard library's `expf` is a call per value). Written with plain
/// multiplies and adds (no fused multiply-add), so it gives the same bits on every CPU and
/// vector width. Relative error below 2e-6 for `e` up to 30 and 5e-6 up to 87: the rounding of
/// `t = -e log2(e)` to single precision (half an ulp of `t`, times ln 2: 1.3e-6 where
/// |t| < 64, 2.6e-6 up to 128), `log2(e)`'s own rounding (1.4e-8 relative, times |t| ln 2)
/// and the polynomial's 1.1e-7.
/// Outside `[0, 87]`, or for NaN, the result is meaningless: callers mask it.
#[inline(always)]
pub fn exp_neg(e: f32) -> f32 {
    // Adding 1.5 * 2^23 rounds to an integer (the ulp there is 1) and leaves that integer in
    // the low bits of the sum.
    const ROUND: f32 = 12_582_912.0;
    let t = -e * std::f32::consts::LOG2_E;
    let rounded = t + ROUND;
    let n = rounded - ROUND;
    let k = (rounded.to_bits() as i32).wrapping_sub(ROUND.to_bits() as i32);
    // 2^f = e^(f ln 2) for f in [-1/2, 1/2]: Taylor to the sixth power (remainder
    // (ln 2 / 2)^7 / 7! = 1.1e-7), by Horner.
    let f = (t - n) * std::f32::consts::LN_2;
    let p = 1.0
        + f * (1.0
            + f * (1.0 / 2.0
                + f * (1.0 / 6.0 + f * (1.0 / 24.0 + f * (1.0 / 120.0 + f * (1.0 / 720.0))))));
    // 2^k as a float: k + 127 in the exponent bits.
    let scale = f32::from_bits((k.wrapping_add(127) as u32) << 23);
    p * scale
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_non_negative_is_round_over_the_range_maps_are_quantised_in() {
        // Every float within a few ulps of each integer and each tie up to 2^16, a sweep, the
        // largest float below 0.5, and NaN (which `as` casts turn into 0 either way).
        let mut values = vec![0.0f32, -0.0, 0.5f32.next_down(), 0.5, f32::NAN];
        for k in 0..=65_536u32 {
            for centre in [k as f32, k as f32 + 0.5] {
                let bits = centre.to_bits() as i64;
                values.extend((-3..=3).map(|d| f32::from_bits((bits + d).max(0) as u32)));
            }
        }
        values.extend((0..1_000_000).map(|i| i as f32 * 0.065_537));
        for v in values {
            let (got, want) = (round_non_negative(v), v.round());
            assert!(
                got == want || (got == 0.0 && want.is_nan()),
                "{v:e}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn exp_neg_is_within_its_stated_error_of_the_exact_exponential() {
        let worst = |from: u32, to: u32| {
            (from..=to)
                .map(|i| {
                    let e = i as f32 * 1e-4;
                    let exact = (-(e as f64)).exp();
                    ((exp_neg(e) as f64 - exact) / exact).abs()
                })
                .fold(0f64, f64::max)
        };
        let (up_to_30, up_to_87) = (worst(0, 300_000), worst(300_000, 870_000));
        assert!(
            up_to_30 < 2e-6,
            "worst relative error up to 30: {up_to_30:e}"
        );
        assert!(
            up_to_87 < 5e-6,
            "worst relative error up to 87: {up_to_87:e}"
        );
        assert_eq!(exp_neg(0.0), 1.0);
    }

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
