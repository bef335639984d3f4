//! Arithmetic on `LANES` pixels at once for the streaming kernel: the floating-point type it
//! computes in, a vector of lanes whose operations LLVM turns into vector instructions, the
//! small symmetric-matrix helpers, and the prefetch of the input planes. No solve logic.

use crate::plane::{prefetch_at, CfaColour, Dark, DnMosaic, DnSamples, Frames, LightFrame, Plane};

/// Pixels processed together (one vector register of f32 on AVX-512, two on AVX2).
pub const LANES: usize = 16;

/// The floating-point type the kernel computes in.
pub trait Real:
    num_traits::Float + Copy + Send + Sync + Default + std::ops::AddAssign + 'static
{
    fn of(v: f64) -> Self;
    fn of32(v: f32) -> Self;
    fn to32(self) -> f32;
}

impl Real for f32 {
    #[inline(always)]
    fn of(v: f64) -> Self {
        v as f32
    }
    #[inline(always)]
    fn of32(v: f32) -> Self {
        v
    }
    #[inline(always)]
    fn to32(self) -> f32 {
        self
    }
}

impl Real for f64 {
    #[inline(always)]
    fn of(v: f64) -> Self {
        v
    }
    #[inline(always)]
    fn of32(v: f32) -> Self {
        v as f64
    }
    #[inline(always)]
    fn to32(self) -> f32 {
        self as f32
    }
}

/// `LANES` values operated on together: each operation is a loop over the lanes, which LLVM
/// turns into vector instructions.
#[derive(Clone, Copy)]
pub struct V<T>(pub [T; LANES]);

// No `array::map` or closures below: code the compiler does not inline into the AVX-512 /
// AVX2 instances is compiled for the baseline CPU, where `mul_add` is a library call (a large
// share of the kernel's time when it happened: docs/solve.md).
impl<T: Real> V<T> {
    #[inline(always)]
    pub fn splat(v: T) -> Self {
        V([v; LANES])
    }
    #[inline(always)]
    pub fn sqrt(self) -> Self {
        let mut out = self.0;
        for v in &mut out {
            *v = v.sqrt();
        }
        V(out)
    }
    #[inline(always)]
    pub fn max(self, floor: T) -> Self {
        let mut out = self.0;
        for v in &mut out {
            // NaN becomes `floor` too.
            *v = if *v > floor { *v } else { floor };
        }
        V(out)
    }
}

macro_rules! lane_op {
    ($trait:ident, $method:ident, $op:tt) => {
        impl<T: Real> std::ops::$trait for V<T> {
            type Output = V<T>;
            #[inline(always)]
            fn $method(self, o: V<T>) -> V<T> {
                let mut out = self.0;
                for l in 0..LANES {
                    out[l] = self.0[l] $op o.0[l];
                }
                V(out)
            }
        }
        impl<T: Real> std::ops::$trait<T> for V<T> {
            type Output = V<T>;
            #[inline(always)]
            fn $method(self, o: T) -> V<T> {
                let mut out = self.0;
                for l in 0..LANES {
                    out[l] = self.0[l] $op o;
                }
                V(out)
            }
        }
    };
}
lane_op!(Add, add, +);
lane_op!(Sub, sub, -);
lane_op!(Mul, mul, *);
lane_op!(Div, div, /);

/// `a * b + c`, fused where the CPU has FMA (`FMA` is only set in code compiled for it: a
/// fused multiply-add without the instruction is a slow library call).
#[inline(always)]
pub fn madd<T: Real, const FMA: bool>(a: T, b: T, c: T) -> T {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// How far ahead of the current chunk (pixels) the input planes are prefetched: the kernel
/// reads ~40 streams at once (30 colour planes, 10 masks), more than the hardware prefetchers
/// track, so without this every chunk waits for memory.
pub const PREFETCH_AHEAD: usize = 256;

/// Asks the CPU to start loading the cache lines at pixel index `i` of every input plane.
#[inline(always)]
pub fn prefetch(frames: &Frames, i: usize) {
    if i >= frames.width * frames.height {
        return;
    }
    if let Some(cfa) = frames.lights.first().and_then(|f| f.cfa.as_ref()) {
        // The frames of a stack share one set of ratio planes.
        cfa.ratios
            .channels()
            .iter()
            .for_each(|p| prefetch_at(&p.data, i));
    }
    // A dn16 set's frames share their dark frame, and so do a RAW stack's kept as DN.
    let first = frames.lights.first();
    if let Some(dark) = first.and_then(|f| f.dn.as_ref()?.dark.as_ref()) {
        dark.prefetch(i);
    }
    if let Some(dark) = first.and_then(|f| f.cfa_dn.as_ref()?.dark.as_ref()) {
        prefetch_at(dark, i);
    }
    for f in &frames.lights {
        f.rgb
            .channels()
            .iter()
            .for_each(|p| prefetch_at(&p.data, i));
        if let Some(dn) = &f.dn {
            dn.prefetch(i);
        }
        if let Some(dn) = &f.cfa_dn {
            dn.prefetch(i);
        }
        if let Some(m) = &f.saturated {
            prefetch_at(&m.data, i);
        }
    }
}

/// `a - p q` where `drop`, else `a`.
#[inline(always)]
pub fn subtract_if<T: Real, const FMA: bool>(drop: bool, a: T, p: T, q: T) -> T {
    if drop {
        madd::<T, FMA>(-p, q, a)
    } else {
        a
    }
}

/// `LANES` values of plane `p` from pixel index `i0`.
#[inline(always)]
pub fn load<T: Real>(p: &Plane, i0: usize) -> [T; LANES] {
    let src: &[f32; LANES] = p.data[i0..i0 + LANES].try_into().expect("a whole chunk");
    let mut out = [T::zero(); LANES];
    for (o, &v) in out.iter_mut().zip(src) {
        *o = T::of32(v);
    }
    out
}

/// `LANES` values of channel `c` of a frame kept as DN from pixel index `i0`, in `T`: the
/// arithmetic of [`DnSamples::value`], here so that it is compiled into (and vectorised with)
/// each kernel.
#[inline(always)]
fn load_dn<T: Real>(dn: &DnSamples, c: usize, i0: usize) -> [T; LANES] {
    let src: &[u16; LANES] = dn.dn[c][i0..i0 + LANES].try_into().expect("a whole chunk");
    let mut values = [0.0f32; LANES];
    for (v, &s) in values.iter_mut().zip(src) {
        *v = dn.linear(s);
    }
    match dn.dark.as_deref() {
        None => {}
        Some(Dark::Planes(planes)) => {
            let dark: &[f32; LANES] = planes.channels()[c].data[i0..i0 + LANES]
                .try_into()
                .expect("a whole chunk");
            for (v, d) in values.iter_mut().zip(dark) {
                *v -= d;
            }
        }
        Some(Dark::Dn(dark)) => {
            let src: &[u16; LANES] = dark.dn[c][i0..i0 + LANES]
                .try_into()
                .expect("a whole chunk");
            for (v, &s) in values.iter_mut().zip(src) {
                *v -= dark.linear(s);
            }
        }
    }
    values.map(T::of32)
}

/// The own CFA samples of the `LANES` pixels of a frame kept as DN from index `i0` (columns
/// `x`.. of row `y`): the arithmetic of [`DnMosaic::value`], here so that it is compiled into
/// (and vectorised with) each kernel.
#[inline(always)]
fn load_cfa_dn(dn: &DnMosaic, i0: usize, (x, y): (usize, usize)) -> [f32; LANES] {
    let src: &[u16; LANES] = dn.dn[i0..i0 + LANES].try_into().expect("a whole chunk");
    let sites = by_column_parity(x, dn.sites[y & 1]);
    let (black, scale) = (sites.map(|s| s.0), sites.map(|s| s.1));
    let mut values = [0.0f32; LANES];
    for (l, (v, &s)) in values.iter_mut().zip(src).enumerate() {
        *v = (s as f32 - black[l]) * scale[l];
    }
    if let Some(dark) = &dn.dark {
        let dark: &[f32; LANES] = dark[i0..i0 + LANES].try_into().expect("a whole chunk");
        for (v, d) in values.iter_mut().zip(dark) {
            *v -= d;
        }
    }
    values
}

/// Per lane of a chunk starting at column `x`, the entry of `by_parity` (indexed by column
/// parity) for the lane's column, as whole-chunk arrays: the lanes alternate between two
/// values, which the compiler can hold in vectors and blend with, where a per-lane index
/// compiled to a scalar load per lane (the kernel's profile before this was in lanes).
#[inline(always)]
fn by_column_parity<P: Copy>(x: usize, by_parity: [P; 2]) -> [P; LANES] {
    let (even, odd) = (by_parity[x & 1], by_parity[(x + 1) & 1]);
    std::array::from_fn(|l| if l & 1 == 0 { even } else { odd })
}

/// Per lane of the chunk at (`x`, `y`), the lane's own CFA channel (0, 1, 2 for R, G, B).
#[inline(always)]
pub fn own_channel(pattern: [[u8; 2]; 2], (x, y): (usize, usize)) -> [u8; LANES] {
    by_column_parity(x, pattern[y & 1])
}

/// Per lane of the chunk at (`x`, `y`), which of R, G, B is the lane's own CFA channel
/// ([`own_channel`] as one mask per channel).
#[inline(always)]
pub fn own_channels(pattern: [[u8; 2]; 2], (x, y): (usize, usize)) -> [[bool; LANES]; 3] {
    let own = own_channel(pattern, (x, y));
    // Plain loops, not `array::map`: the compiler is free to call a `map` out of line, and
    // did once an unrelated change moved its inlining budget (the 16 MP solve stage then took
    // 0.9 s instead of 0.6, a call per chunk and channel compiled without the kernel's vector
    // features).
    let mut masks = [[false; LANES]; 3];
    for (c, mask) in masks.iter_mut().enumerate() {
        for (m, &o) in mask.iter_mut().zip(&own) {
            *m = o as usize == c;
        }
    }
    masks
}

/// The R, G, B values of the `LANES` pixels of `frame` from index `i0` (columns `x`.. of row
/// `y`), in `T`, however the frame stores them (see `LightFrame::cfa`).
#[inline(always)]
pub fn load_rgb<T: Real>(frame: &LightFrame, i0: usize, (x, y): (usize, usize)) -> [[T; LANES]; 3] {
    if let Some(dn) = &frame.dn {
        return [load_dn(dn, 0, i0), load_dn(dn, 1, i0), load_dn(dn, 2, i0)];
    }
    let Some(cfa) = &frame.cfa else {
        return [
            load(&frame.rgb.r, i0),
            load(&frame.rgb.g, i0),
            load(&frame.rgb.b, i0),
        ];
    };
    let own = match &frame.cfa_dn {
        Some(dn) => load_cfa_dn(dn, i0, (x, y)),
        None => frame.rgb.g.data[i0..i0 + LANES]
            .try_into()
            .expect("a whole chunk"),
    };
    cfa_rgb(cfa, &own, i0, (x, y))
}

/// [`CfaColour::rgb`] of the `LANES` pixels from index `i0` (columns `x`.. of row `y`) whose
/// own samples are `own`, in lanes: the same arithmetic in the same order (so the same bits),
/// with the lanes' own channels and illuminant colours as alternating lane constants.
#[inline(always)]
fn cfa_rgb<T: Real>(
    cfa: &CfaColour,
    own: &[f32; LANES],
    i0: usize,
    (x, y): (usize, usize),
) -> [[T; LANES]; 3] {
    let is_own = own_channels(cfa.pattern, (x, y));
    let pattern_row = cfa.pattern[y & 1].map(|c| cfa.colour[c as usize]);
    let own_colour = by_column_parity(x, pattern_row);
    let ratios = cfa.ratios.channels();
    // Channel by channel through an inlined function, not `array::from_fn` over a closure:
    // that closure was compiled out of line, without the kernel's vector features, and called
    // three times per light (its results went through memory: a tenth of the kernel's time).
    let ratio = |c: usize| (&ratios[c].data[i0..i0 + LANES], cfa.colour[c]);
    [
        cfa_channel(own, ratio(0), &own_colour, &is_own[0]),
        cfa_channel(own, ratio(1), &own_colour, &is_own[1]),
        cfa_channel(own, ratio(2), &own_colour, &is_own[2]),
    ]
}

/// One channel of [`cfa_rgb`] from its `(ratios, colour)`: the own sample where the lane's own
/// channel is this one, else the sample times the lane's ratio and this channel's illuminant
/// colour over the own channel's.
#[inline(always)]
fn cfa_channel<T: Real>(
    own: &[f32; LANES],
    (ratio, colour): (&[f32], f32),
    own_colour: &[f32; LANES],
    is_own: &[bool; LANES],
) -> [T; LANES] {
    let ratio: &[f32; LANES] = ratio.try_into().expect("a whole chunk");
    // Every lane's scaled value first, then the selects: with the division inside the select,
    // the compiler branched around it lane by lane.
    let mut scaled = [0.0f32; LANES];
    for l in 0..LANES {
        scaled[l] = own[l] * ratio[l] * colour / own_colour[l];
    }
    let mut out = [T::zero(); LANES];
    for l in 0..LANES {
        out[l] = T::of32(if is_own[l] { own[l] } else { scaled[l] });
    }
    out
}

/// Writes `v` to `out` (`LANES` values) in `f32`.
#[inline(always)]
pub fn store<T: Real>(out: &mut [f32], v: &V<T>) {
    for (o, v) in out.iter_mut().zip(&v.0) {
        *o = v.to32();
    }
}

/// Squared Frobenius norm of a symmetric 3x3 matrix stored as (xx, xy, xz, yy, yz, zz).
#[inline(always)]
pub fn frob_sq<T: Real>(m: &[V<T>; 6]) -> V<T> {
    m[0] * m[0] + m[3] * m[3] + m[5] * m[5] + (m[1] * m[1] + m[2] * m[2] + m[4] * m[4]) * T::of(2.0)
}

/// The index in the symmetric layout of [`frob_sq`] of entry `(i, j)`.
pub const SYM: [[usize; 3]; 3] = [[0, 1, 2], [1, 3, 4], [2, 4, 5]];

/// The six vectors of a symmetric matrix held as lane arrays (layout of [`frob_sq`]).
#[inline(always)]
pub fn vectors6<T: Real>(m: &[[T; LANES]; 6]) -> [V<T>; 6] {
    [V(m[0]), V(m[1]), V(m[2]), V(m[3]), V(m[4]), V(m[5])]
}

/// The adjugate of the symmetric matrix `m` (layout of [`frob_sq`]), symmetric too: the
/// inverse times the determinant.
#[inline(always)]
pub fn adjugate<T: Real>(m: &[V<T>; 6]) -> [V<T>; 6] {
    let [xx, xy, xz, yy, yz, zz] = *m;
    [
        yy * zz - yz * yz,
        xz * yz - xy * zz,
        xy * yz - xz * yy,
        xx * zz - xz * xz,
        xy * xz - xx * yz,
        xx * yy - xy * xy,
    ]
}

/// `m s m` for the symmetric matrices `m` and `s` (layout of [`frob_sq`]).
#[inline(always)]
pub fn sandwich<T: Real>(m: &[V<T>; 6], s: &[V<T>; 6]) -> [V<T>; 6] {
    // t = m s, then t m on and above the diagonal (loops with constant bounds unroll).
    let mut t = [[V::splat(T::zero()); 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            t[i][j] = m[SYM[i][0]] * s[SYM[0][j]]
                + m[SYM[i][1]] * s[SYM[1][j]]
                + m[SYM[i][2]] * s[SYM[2][j]];
        }
    }
    let mut out = [V::splat(T::zero()); 6];
    for i in 0..3 {
        for j in i..3 {
            out[SYM[i][j]] =
                t[i][0] * m[SYM[0][j]] + t[i][1] * m[SYM[1][j]] + t[i][2] * m[SYM[2][j]];
        }
    }
    out
}

/// The symmetric matrix `m` (layout of [`frob_sq`]) times `v`.
#[inline(always)]
pub fn apply<T: Real>(m: &[V<T>; 6], v: &[V<T>; 3]) -> [V<T>; 3] {
    [
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[1] * v[0] + m[3] * v[1] + m[4] * v[2],
        m[2] * v[0] + m[4] * v[1] + m[5] * v[2],
    ]
}

/// Component `d` of the luminance combination of three per-channel vectors.
#[inline(always)]
pub fn mix<T: Real>(v: &[[V<T>; 3]; 3], d: usize, wt: &[T; 3]) -> V<T> {
    v[0][d] * wt[0] + v[1][d] * wt[1] + v[2][d] * wt[2]
}

#[inline(always)]
pub fn vectors<T: Real>(v: &[[T; LANES]; 3]) -> [V<T>; 3] {
    [V(v[0]), V(v[1]), V(v[2])]
}

#[inline(always)]
pub fn dot<T: Real>(a: &[V<T>; 3], b: &[V<T>; 3]) -> V<T> {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::plane::{Mask, Plane, RgbPlanes};

    /// A frame of CFA samples kept as DN (with a dark frame), with ratios and DN that differ
    /// from pixel to pixel, so a lane that read another lane's site, channel or colour would
    /// show.
    fn cfa_dn_frame(width: usize, height: usize, pattern: [[u8; 2]; 2]) -> LightFrame {
        let n = width * height;
        let wave = |i: usize, k: usize| ((i * 7 + k * 13) % 97) as f32 / 97.0;
        let plane = |k: usize| Plane {
            width,
            height,
            data: (0..n).map(|i| 0.3 + 2.0 * wave(i, k)).collect(),
        };
        let ratios = RgbPlanes {
            r: plane(1),
            g: plane(2),
            b: plane(3),
        };
        let samples = DnMosaic {
            width,
            height,
            dn: (0..n).map(|i| 600 + (i * 4099 % 60_000) as u16).collect(),
            sites: [
                [(512.0, 1.0 / 15_000.0), (520.0, 1.0 / 15_500.0)],
                [(508.0, 1.0 / 16_000.0), (515.0, 1.0 / 15_800.0)],
            ],
            dark: Some(Arc::new((0..n).map(|i| 1e-3 * wave(i, 4)).collect())),
        };
        let cfa = CfaColour {
            pattern,
            ratios: Arc::new(ratios),
            colour: [0.61, 1.0, 0.83],
        };
        LightFrame::from_cfa_dn(samples, None::<Mask>, cfa)
    }

    #[test]
    fn a_cfa_chunk_loads_what_each_pixel_reads_bit_for_bit() {
        let (width, height) = (LANES + 7, 4);
        for pattern in [[[0, 1], [1, 2]], [[1, 0], [2, 1]], [[2, 1], [1, 0]]] {
            let frame = cfa_dn_frame(width, height, pattern);
            let cfa = frame.cfa.as_ref().expect("a CFA frame");
            // Every chunk start parity on both row parities.
            for (x, y) in [(0, 0), (1, 0), (6, 1), (7, 3)] {
                let i0 = y * width + x;
                let lanes: [[f32; LANES]; 3] = load_rgb(&frame, i0, (x, y));
                let own = own_channels(pattern, (x, y));
                for l in 0..LANES {
                    let sample = frame.cfa_sample(i0 + l, x + l, y);
                    let expected = cfa.rgb(sample, i0 + l, cfa.own(x + l, y));
                    for c in 0..3 {
                        assert_eq!(
                            lanes[c][l].to_bits(),
                            expected[c].to_bits(),
                            "pattern {pattern:?}, chunk ({x}, {y}), lane {l}, channel {c}"
                        );
                        assert_eq!(own[c][l], cfa.own(x + l, y) == c);
                    }
                }
            }
        }
    }
}
