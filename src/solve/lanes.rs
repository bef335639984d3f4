//! Arithmetic on `LANES` pixels at once for the streaming kernel: the floating-point type it
//! computes in, a vector of lanes whose operations LLVM turns into vector instructions, the
//! small symmetric-matrix helpers, and the prefetch of the input planes. No solve logic.

use crate::plane::{prefetch_at, Dark, DnMosaic, DnSamples, Frames, LightFrame, Plane};

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
    let sites = dn.sites[y & 1];
    let mut values = [0.0f32; LANES];
    for (l, (v, &s)) in values.iter_mut().zip(src).enumerate() {
        let (black, scale) = sites[(x + l) & 1];
        *v = (s as f32 - black) * scale;
    }
    if let Some(dark) = &dn.dark {
        let dark: &[f32; LANES] = dark[i0..i0 + LANES].try_into().expect("a whole chunk");
        for (v, d) in values.iter_mut().zip(dark) {
            *v -= d;
        }
    }
    values
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
    let mut out = [[T::zero(); LANES]; 3];
    for (l, &v) in own.iter().enumerate() {
        let rgb = cfa.rgb(v, i0 + l, cfa.own(x + l, y));
        for c in 0..3 {
            out[c][l] = T::of32(rgb[c]);
        }
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
