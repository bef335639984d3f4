//! The sRGB transfer curve (IEC 61966-2-1), and linear values quantised through it to 8 or
//! 16 bits from a table instead of a `powf` per value: `albedo.png` holds 48 M such values at
//! 16 MP, and the report page's loupe as many again. The table gives the code the direct
//! computation gives, for every `f32`.
//!
//! How: a value's code rises with the value, and the values order as their bit patterns do.
//! So the table holds, per code, the least value that reaches it (found by bisection over the
//! bit patterns, with the direct computation), and per bin of bit patterns the code at the
//! bin's lower edge; a lookup starts there and steps up past the thresholds the value reaches.
//! The bins are slices of the bit patterns, so each spans the same fraction of its value (a
//! 2^-16 of its binade) and, where the curve is steepest per fraction (near 1), under half a
//! 16-bit code: most lookups step over no threshold. (With bins eight times as wide, up to
//! four codes each, the stepping's unpredictable branches made the table slower than the
//! `powf` it replaces.) Values on the curve's linear part (at most 0.0031308), at or above 1
//! and NaN are computed directly: no `powf` there.

use std::sync::OnceLock;

use rayon::prelude::*;

use crate::math::round_non_negative;

/// Where the sRGB curve's linear part ends (IEC 61966-2-1).
const LINEAR_END: f32 = 0.003_130_8;

/// Linear to sRGB-encoded (IEC 61966-2-1), clamped to [0, 1].
#[inline]
pub fn linear_to_srgb(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0);
    if v <= LINEAR_END {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// sRGB-encoded to linear (IEC 61966-2-1), the inverse of [`linear_to_srgb`]; not clamped.
#[inline]
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.040_45 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// Bit patterns per bin: 2^7, so 2^16 bins per binade (1.1 MB of start codes per table).
const BIN_SHIFT: u32 = 7;

/// A quantiser of linear values through the sRGB curve to `0..=levels`.
pub struct SrgbTable {
    /// The code by direct computation.
    direct: fn(f32) -> u16,
    /// The bit pattern of bin 0's lower edge.
    base: u32,
    /// `thresholds[k]`: the least value above [`LINEAR_END`] whose code is at least `k`
    /// (infinity where no value below 1 reaches it).
    thresholds: Vec<f32>,
    /// Per bin, the code at its lower edge (or at the first value above [`LINEAR_END`]).
    start: Vec<u16>,
}

impl SrgbTable {
    fn new(levels: u16, direct: fn(f32) -> u16) -> SrgbTable {
        let first = LINEAR_END.to_bits() + 1;
        let last = 1.0f32.to_bits() - 1;
        let thresholds = (0..=levels as u32)
            .into_par_iter()
            .map(|k| {
                // The least pattern in [first, last + 1) whose code is at least k.
                let (mut lo, mut hi) = (first, last + 1);
                while lo < hi {
                    let mid = lo + (hi - lo) / 2;
                    if direct(f32::from_bits(mid)) as u32 >= k {
                        hi = mid;
                    } else {
                        lo = mid + 1;
                    }
                }
                if lo > last {
                    f32::INFINITY
                } else {
                    f32::from_bits(lo)
                }
            })
            .collect();
        let base = first >> BIN_SHIFT << BIN_SHIFT;
        let bins = ((last - base) >> BIN_SHIFT) + 1;
        let start = (0..bins)
            .into_par_iter()
            .map(|b| direct(f32::from_bits((base + (b << BIN_SHIFT)).max(first))))
            .collect();
        SrgbTable {
            direct,
            base,
            thresholds,
            start,
        }
    }

    /// The code of `v`, as `direct(v)` gives it.
    #[inline]
    pub fn code(&self, v: f32) -> u16 {
        // NaN fails the first test and takes the direct path.
        if !(v > LINEAR_END && v < 1.0) {
            return (self.direct)(v);
        }
        let bin = ((v.to_bits() - self.base) >> BIN_SHIFT) as usize;
        let mut k = self.start[bin];
        while self.thresholds.get(k as usize + 1).is_some_and(|&t| v >= t) {
            k += 1;
        }
        k
    }
}

/// `round(linear_to_srgb(v) * 65535)`, as `albedo.png` stores a sample.
pub fn srgb16_direct(v: f32) -> u16 {
    round_non_negative(linear_to_srgb(v) * 65535.0) as u16
}

/// `round(linear_to_srgb(v) * 255)`, as the report page's 8-bit views hold a sample.
pub fn srgb8_direct(v: f32) -> u16 {
    (linear_to_srgb(v).clamp(0.0, 1.0) * 255.0).round() as u16
}

/// The 16-bit table ([`srgb16_direct`]), built on first use (tens of milliseconds).
pub fn srgb16() -> &'static SrgbTable {
    static TABLE: OnceLock<SrgbTable> = OnceLock::new();
    built_once(&TABLE, || SrgbTable::new(u16::MAX, srgb16_direct))
}

/// The 8-bit table ([`srgb8_direct`]), built on first use.
pub fn srgb8() -> &'static SrgbTable {
    static TABLE: OnceLock<SrgbTable> = OnceLock::new();
    built_once(&TABLE, || SrgbTable::new(u8::MAX as u16, srgb8_direct))
}

/// `cell`'s table, built by `build` on first use. Not in `OnceLock::get_or_init`: the build
/// runs on rayon's pool, and a worker that took part of it could, while it waits inside, pick
/// up another job that asks for the table and then wait on the lock, which the builder holds
/// until that worker is done: both wait for ever (two `cargo test` threads hung so, with both
/// workers parked). So the lock is never held while building: two first users may both build
/// the table, and the first one set is kept.
fn built_once(
    cell: &'static OnceLock<SrgbTable>,
    build: impl FnOnce() -> SrgbTable,
) -> &'static SrgbTable {
    if let Some(table) = cell.get() {
        return table;
    }
    let _ = cell.set(build());
    cell.get().expect("set above or by another thread")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every bit pattern from `from` to `to` (inclusive) whose code differs between the table
    /// and the direct computation, at most a few.
    fn mismatches(table: &SrgbTable, from: u32, to: u32) -> Vec<(f32, u16, u16)> {
        (from..=to)
            .into_par_iter()
            .map(f32::from_bits)
            .filter_map(|v| {
                let (got, want) = (table.code(v), (table.direct)(v));
                (got != want).then_some((v, got, want))
            })
            .take_any(5)
            .collect()
    }

    #[test]
    fn the_16_bit_table_gives_the_direct_code_for_every_value_on_the_curve() {
        // Every float from the end of the linear part to 1: 70 million values, the whole
        // range the table serves.
        let table = srgb16();
        let (from, to) = (LINEAR_END.to_bits(), 1.0f32.to_bits());
        assert_eq!(mismatches(table, from, to), vec![]);
    }

    #[test]
    fn the_tables_take_the_direct_path_outside_the_curve() {
        for table in [srgb16(), srgb8()] {
            for v in [
                f32::NAN,
                -1.0,
                -0.0,
                0.0,
                1e-30,
                0.001,
                LINEAR_END,
                1.0,
                1.5,
                f32::INFINITY,
            ] {
                assert_eq!(table.code(v), (table.direct)(v), "at {v:e}");
            }
        }
        assert_eq!(srgb16().code(1.0), 65535);
        assert_eq!(srgb8().code(0.5), 188);
    }

    #[test]
    fn the_8_bit_table_gives_the_direct_byte() {
        // Every 7th float from the end of the linear part to 1 (10 million values).
        let table = srgb8();
        let bits = (LINEAR_END.to_bits()..=1.0f32.to_bits()).step_by(7);
        for v in bits.map(f32::from_bits) {
            assert_eq!(table.code(v), srgb8_direct(v), "at {v:e}");
        }
    }
}
