//! A woven textile as an analytic height field and albedo over the table (world metres):
//! warp threads along y and weft threads along x, crossing over and under in a plain or twill
//! weave, each with an elliptic-ish cross-section, crimp where it dives under its neighbour,
//! twisted fibre ridges, a plaid colour sett, and slow folds across the whole sample.

use serde::{Deserialize, Serialize};

/// How the warp and weft threads cross over and under each other.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Weave {
    /// Over one, under one.
    Plain,
    /// Over two, under two, shifting by one thread per row: diagonal ribs.
    Twill,
}

/// Everything that defines the textile; seeded and deterministic.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Textile {
    /// The weave pattern.
    pub weave: Weave,
    /// Centre-to-centre thread spacing.
    pub thread_pitch_m: f64,
    /// Fraction of the pitch a thread covers; the rest is gap down to the backing.
    pub thread_fill: f64,
    /// Height of a thread's crown above its edges.
    pub thread_height_m: f64,
    /// Up/down travel of a thread as it goes over and under the crossing threads.
    pub crimp_m: f64,
    /// Spacing and depth of the twisted fibre ridges along each thread.
    pub fibre_period_m: f64,
    /// Depth of those fibre ridges (metres).
    pub fibre_depth_m: f64,
    /// How far the fibre ridges slant from straight across the thread (degrees).
    pub twist_deg: f64,
    /// Slow folds of the sample (large-scale normal variation).
    pub fold_amplitude_m: f64,
    /// Wavelength of the folds (metres).
    pub fold_wavelength_m: f64,
    /// Linear albedo of the thread colours, and the plaid sett as (colour, thread count)
    /// stripes repeated across both warp and weft.
    pub palette: Vec<[f64; 3]>,
    /// The plaid sett: `(palette index, thread count)` stripes, in order, repeated across both warp
    /// and weft.
    pub sett: Vec<(usize, usize)>,
    /// Albedo of the backing seen through the gaps.
    pub gap_albedo: [f64; 3],
    /// Seed of the per-thread variation (the phase of each thread's fibre ridges).
    pub seed: u64,
}

impl Default for Textile {
    /// A tartan twill: threads 0.9 mm apart, ridged fibres, gentle folds.
    fn default() -> Self {
        Textile {
            weave: Weave::Twill,
            thread_pitch_m: 0.9e-3,
            thread_fill: 0.88,
            thread_height_m: 0.2e-3,
            crimp_m: 0.05e-3,
            fibre_period_m: 0.35e-3,
            fibre_depth_m: 0.012e-3,
            twist_deg: 35.0,
            fold_amplitude_m: 1.0e-3,
            fold_wavelength_m: 0.07,
            palette: vec![
                [0.42, 0.05, 0.05],  // red
                [0.04, 0.16, 0.07],  // green
                [0.035, 0.05, 0.17], // navy
                [0.70, 0.64, 0.46],  // cream
                [0.55, 0.45, 0.06],  // yellow
            ],
            sett: vec![
                (0, 10),
                (2, 4),
                (0, 2),
                (1, 8),
                (3, 2),
                (1, 8),
                (4, 1),
                (2, 6),
            ],
            gap_albedo: [0.05, 0.05, 0.05],
            seed: 1886,
        }
    }
}

/// Which part of the weave is on top at a point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Visible {
    /// Warp thread `i` is on top (warp threads run along y; thread `i` spans x from `i` to
    /// `i + 1` pitches).
    Warp(i64),
    /// Weft thread `j` is on top (weft threads run along x; thread `j` spans y from `j` to
    /// `j + 1` pitches).
    Weft(i64),
    /// No thread: the backing seen through the gap between threads.
    Gap,
}

/// Height (m, relative to the sample's mean plane) and what is on top there.
#[derive(Clone, Copy, Debug)]
pub struct SurfacePoint {
    /// Height of the surface above the sample's mean plane, metres, folds included.
    pub height: f64,
    /// The thread (or gap) on top there.
    pub visible: Visible,
    /// Fibre ridge phase in [-1, 1] at the visible thread (albedo varies with it).
    pub ridge: f64,
}

impl Textile {
    /// True where warp thread `i` lies over weft thread `j`.
    fn warp_over(&self, i: i64, j: i64) -> bool {
        match self.weave {
            Weave::Plain => (i + j).rem_euclid(2) == 0,
            Weave::Twill => (j - i).rem_euclid(4) < 2,
        }
    }

    /// Height of one thread at `along`/`across` (m) in its own frame; `None` off the thread.
    /// `over` tells, for crossing index `c`, whether this thread is on top there.
    fn thread_height(
        &self,
        index: i64,
        across: f64,
        along: f64,
        over: impl Fn(i64) -> bool,
    ) -> Option<(f64, f64)> {
        let p = self.thread_pitch_m;
        let half_width = 0.5 * self.thread_fill * p;
        let offset = across - (index as f64 + 0.5) * p;
        let s = offset / half_width;
        if s.abs() > 1.0 {
            return None;
        }
        let profile = self.thread_height_m * (1.0 - s * s);
        // Crimp: +1 over a crossing, -1 under it, eased between crossing centres.
        let t = along / p - 0.5;
        let c0 = t.floor();
        let f = t - c0;
        let sign = |c: i64| if over(c) { 1.0 } else { -1.0 };
        let (s0, s1) = (sign(c0 as i64), sign(c0 as i64 + 1));
        let ease = 0.5 - 0.5 * (std::f64::consts::PI * f).cos();
        let crimp = self.crimp_m * (s0 + (s1 - s0) * ease);
        // Twisted fibres: ridges slanted by the twist angle, fading toward the edges.
        let phase_offset = (splitmix(self.seed ^ index as u64) % 1000) as f64 / 1000.0;
        let phase = (along + offset * self.twist_deg.to_radians().tan()) / self.fibre_period_m
            + phase_offset;
        let ridge = (std::f64::consts::TAU * phase).sin();
        let fibres = self.fibre_depth_m * ridge * (1.0 - s * s);
        Some((profile + crimp + fibres, ridge))
    }

    /// Slow folds: a few long sinusoids (low-frequency slope of a few degrees).
    fn fold(&self, x: f64, y: f64) -> f64 {
        let k = std::f64::consts::TAU / self.fold_wavelength_m;
        self.fold_amplitude_m
            * (0.6 * (k * x + 0.3).sin() * (0.8 * k * y + 1.1).sin()
                + 0.4 * (0.55 * k * (x + y) + 2.0).sin())
    }

    /// The surface at world point `(x, y)`.
    pub fn surface_at(&self, x: f64, y: f64) -> SurfacePoint {
        let p = self.thread_pitch_m;
        let i = (x / p).floor() as i64;
        let j = (y / p).floor() as i64;
        let warp = self.thread_height(i, x, y, |c| self.warp_over(i, c));
        let weft = self.thread_height(j, y, x, |c| !self.warp_over(c, j));
        let gap_floor = -0.5 * self.thread_height_m;
        let mut best = SurfacePoint {
            height: gap_floor,
            visible: Visible::Gap,
            ridge: 0.0,
        };
        if let Some((h, ridge)) = warp {
            if h > best.height {
                best = SurfacePoint {
                    height: h,
                    visible: Visible::Warp(i),
                    ridge,
                };
            }
        }
        if let Some((h, ridge)) = weft {
            if h > best.height {
                best = SurfacePoint {
                    height: h,
                    visible: Visible::Weft(j),
                    ridge,
                };
            }
        }
        best.height += self.fold(x, y);
        best
    }

    /// Height of the surface at world point `(x, y)` above the sample's mean plane, metres.
    pub fn height_at(&self, x: f64, y: f64) -> f64 {
        self.surface_at(x, y).height
    }

    /// Unit surface normal at `(x, y)` from central differences of the height field.
    pub fn normal_at(&self, x: f64, y: f64) -> [f64; 3] {
        const STEP: f64 = 0.5e-6;
        let dhdx = (self.height_at(x + STEP, y) - self.height_at(x - STEP, y)) / (2.0 * STEP);
        let dhdy = (self.height_at(x, y + STEP) - self.height_at(x, y - STEP)) / (2.0 * STEP);
        let norm = (dhdx * dhdx + dhdy * dhdy + 1.0).sqrt();
        [-dhdx / norm, -dhdy / norm, 1.0 / norm]
    }

    /// Colour of the thread with index `index` in the plaid sett.
    fn thread_colour(&self, index: i64) -> [f64; 3] {
        let total: usize = self.sett.iter().map(|s| s.1).sum();
        let mut n = index.rem_euclid(total.max(1) as i64) as usize;
        for &(colour, count) in &self.sett {
            if n < count {
                return self.palette[colour];
            }
            n -= count;
        }
        self.palette[0]
    }

    /// Diffuse albedo at a surface point: the thread's colour, a little lighter on the fibre
    /// ridges and darker in their grooves.
    pub fn albedo(&self, point: &SurfacePoint) -> [f64; 3] {
        let (base, ridge) = match point.visible {
            Visible::Warp(i) => (self.thread_colour(i), point.ridge),
            Visible::Weft(j) => (self.thread_colour(j), point.ridge),
            Visible::Gap => (self.gap_albedo, 0.0),
        };
        let shade = 1.0 + 0.08 * ridge;
        base.map(|c| (c * shade).min(1.0))
    }

    /// Tallest the surface can be (for shadow marching).
    pub fn max_height(&self) -> f64 {
        self.thread_height_m + self.crimp_m + self.fibre_depth_m + self.fold_amplitude_m
    }

    /// Lowest the surface can be: the gaps' floor at the bottom of a fold (metres, relative to the
    /// mean plane).
    pub fn min_height(&self) -> f64 {
        -0.5 * self.thread_height_m - self.fold_amplitude_m
    }
}

/// A 64-bit mixing function (splitmix64) for deterministic per-thread variation.
pub fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heights_stay_within_the_declared_bounds() {
        let t = Textile::default();
        for k in 0..20_000 {
            let x = (k as f64 * 0.000_137) % 0.05 - 0.025;
            let y = (k as f64 * 0.000_291) % 0.05 - 0.025;
            let h = t.height_at(x, y);
            assert!(h <= t.max_height() + 1e-12 && h >= t.min_height() - 1e-12);
        }
    }

    #[test]
    fn normals_are_unit_and_upward_with_both_warp_and_weft_visible() {
        let t = Textile::default();
        let (mut warp, mut weft, mut gap) = (0, 0, 0);
        let mut max_tilt: f64 = 0.0;
        for k in 0..10_000 {
            let x = (k % 100) as f64 * 0.000_07;
            let y = (k / 100) as f64 * 0.000_07;
            let n = t.normal_at(x, y);
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            assert!((len - 1.0).abs() < 1e-12 && n[2] > 0.0);
            max_tilt = max_tilt.max(n[2].acos().to_degrees());
            match t.surface_at(x, y).visible {
                Visible::Warp(_) => warp += 1,
                Visible::Weft(_) => weft += 1,
                Visible::Gap => gap += 1,
            }
        }
        assert!(warp > 2000 && weft > 2000 && gap > 0, "{warp} {weft} {gap}");
        // Real threads: steep flanks, but no surface facing sideways.
        assert!(max_tilt > 30.0 && max_tilt < 80.0, "max tilt {max_tilt}");
    }

    #[test]
    fn the_sett_gives_a_plaid() {
        let t = Textile::default();
        assert_eq!(t.thread_colour(0), t.palette[0]);
        assert_eq!(t.thread_colour(10), t.palette[2]);
        let total: usize = t.sett.iter().map(|s| s.1).sum();
        assert_eq!(t.thread_colour(total as i64), t.thread_colour(0));
        assert_eq!(t.thread_colour(-1), t.thread_colour(total as i64 - 1));
    }
}
