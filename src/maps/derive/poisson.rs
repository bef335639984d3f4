//! Height over a mask that is not the whole rectangle (an object on a background, holes
//! where pixels were not solved): the least-squares surface whose differences between
//! neighbouring solved pixels best match their slopes, with no constraint across the mask's
//! edge. Frankot-Chellappa cannot leave pixels out; it treats the background as a flat floor
//! glued to the object, and the object's silhouette (a depth step) then bends the whole
//! surface. Here the normal equations (a graph Laplacian over the solved pixels) are solved
//! by conjugate gradients, preconditioned by each pixel's neighbour count, starting from the
//! Fourier solution so that only what the mask changes is left to iterate.

use rayon::prelude::*;
use serde::Serialize;

/// Relative residual `|b - A z| / |b|` at which [`refine`]'s callers stop: the solved
/// pixels' slopes are then matched to a ten-thousandth of their own size, well below the
/// noise of a measured normal (a degree is 1.7 % of a slope). A residual says little about
/// the smoothest error modes; `height`'s tests check the stop against the converged surface,
/// and `scripts/check_masked_height.py` against a sparse direct solve.
pub const TOLERANCE: f64 = 1e-4;

/// How the masked solve ended, for the derive report.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct MaskedSolve {
    /// Pixels integrated (solved ones); the others hold height 0.
    pub pixels: usize,
    /// Conjugate-gradient iterations run.
    pub iterations: usize,
    /// `|b - A z| / |b|` at the end (0 when there was nothing to match).
    pub relative_residual: f64,
}

/// Which of a pixel's four neighbours it is linked to (both solved): bit flags.
const LEFT: u8 = 1;
const RIGHT: u8 = 2;
const UP: u8 = 4;
const DOWN: u8 = 8;

/// The grid's links, one byte of flags per pixel, worked out once: the iteration's stencil
/// then reads a byte instead of testing the mask and the borders four times per pixel.
struct Graph {
    width: usize,
    height: usize,
    links: Vec<u8>,
}

impl Graph {
    /// Neighbours `i` and `j` are linked when both are solved (across the left/right and
    /// top/bottom edges too when `wrap`).
    fn new(width: usize, height: usize, solved: &[bool], wrap: bool) -> Self {
        let n = width * height;
        let mut links = vec![0u8; n];
        links
            .par_chunks_mut(width)
            .enumerate()
            .for_each(|(y, row)| {
                for (x, flags) in row.iter_mut().enumerate() {
                    let i = y * width + x;
                    if !solved[i] {
                        continue;
                    }
                    let graph = Offsets {
                        width,
                        height,
                        wrap,
                    };
                    let linked = |j: Option<usize>| j.is_some_and(|j| solved[j]);
                    *flags = (linked(graph.left(x, y)) as u8 * LEFT)
                        | (linked(graph.right(x, y)) as u8 * RIGHT)
                        | (linked(graph.up(x, y)) as u8 * UP)
                        | (linked(graph.down(x, y)) as u8 * DOWN);
                }
            });
        Graph {
            width,
            height,
            links,
        }
    }

    /// The index of each linked neighbour of pixel `(x, y)`, in the order left, right, up,
    /// down (`None` where not linked).
    #[inline]
    fn neighbours(&self, x: usize, y: usize) -> [Option<usize>; 4] {
        let flags = self.links[y * self.width + x];
        let offsets = Offsets {
            width: self.width,
            height: self.height,
            wrap: true,
        };
        let pick = |bit: u8, j: Option<usize>| if flags & bit != 0 { j } else { None };
        [
            pick(LEFT, offsets.left(x, y)),
            pick(RIGHT, offsets.right(x, y)),
            pick(UP, offsets.up(x, y)),
            pick(DOWN, offsets.down(x, y)),
        ]
    }

    /// `out = A z` (`(A z)_i = deg_i z_i - sum of z over i's neighbours`), returning
    /// `z . A z`.
    fn apply(&self, z: &[f64], out: &mut [f64]) -> f64 {
        let w = self.width;
        out.par_chunks_mut(w)
            .enumerate()
            .map(|(y, row)| {
                let mut curvature = 0.0f64;
                for (x, o) in row.iter_mut().enumerate() {
                    let i = y * w + x;
                    let (mut degree, mut sum) = (0.0f64, 0.0f64);
                    for j in self.neighbours(x, y).into_iter().flatten() {
                        degree += 1.0;
                        sum += z[j];
                    }
                    *o = degree * z[i] - sum;
                    curvature += z[i] * *o;
                }
                curvature
            })
            .sum()
    }

    /// The normal equations' right-hand side for slopes `p = dz/dcolumn`, `q = dz/drow`:
    /// each link's target difference is the mean of its two pixels' slopes along it, and
    /// `b_i` sums the targets of links arriving at `i` minus those leaving it.
    fn divergence(&self, p: &[f32], q: &[f32]) -> Vec<f64> {
        let w = self.width;
        (0..p.len())
            .into_par_iter()
            .map(|i| {
                let [left, right, up, down] = self.neighbours(i % w, i / w);
                let mean = |s: &[f32], j: Option<usize>| {
                    j.map_or(0.0, |j| 0.5 * (s[i] as f64 + s[j] as f64))
                };
                mean(p, left) - mean(p, right) + mean(q, up) - mean(q, down)
            })
            .collect()
    }

    /// `1 / deg_i` (0 for a pixel with no links: it takes no part in the solve).
    fn inverse_degrees(&self) -> Vec<f64> {
        self.links
            .par_iter()
            .map(|&flags| match flags.count_ones() {
                0 => 0.0,
                d => 1.0 / d as f64,
            })
            .collect()
    }
}

/// Neighbour indices on a `width x height` grid, wrapping at the edges when `wrap`.
struct Offsets {
    width: usize,
    height: usize,
    wrap: bool,
}

impl Offsets {
    #[inline]
    fn at(&self, x: usize, y: usize) -> Option<usize> {
        Some(y * self.width + x)
    }
    #[inline]
    fn left(&self, x: usize, y: usize) -> Option<usize> {
        match x {
            0 if self.wrap && self.width > 1 => self.at(self.width - 1, y),
            0 => None,
            _ => self.at(x - 1, y),
        }
    }
    #[inline]
    fn right(&self, x: usize, y: usize) -> Option<usize> {
        if x + 1 < self.width {
            self.at(x + 1, y)
        } else if self.wrap && self.width > 1 {
            self.at(0, y)
        } else {
            None
        }
    }
    #[inline]
    fn up(&self, x: usize, y: usize) -> Option<usize> {
        match y {
            0 if self.wrap && self.height > 1 => self.at(x, self.height - 1),
            0 => None,
            _ => self.at(x, y - 1),
        }
    }
    #[inline]
    fn down(&self, x: usize, y: usize) -> Option<usize> {
        if y + 1 < self.height {
            self.at(x, y + 1)
        } else if self.wrap && self.height > 1 {
            self.at(x, 0)
        } else {
            None
        }
    }
}

/// Refines `z` (a starting surface, e.g. the Fourier solution of the same slopes) into the
/// least-squares surface over the `solved` pixels of a `width x height` grid, at most
/// `max_iterations` steps or relative residual `tolerance` ([`TOLERANCE`]); pixels outside
/// the mask end at 0 and the solved ones have zero mean.
pub fn refine(
    z: &mut [f32],
    (p, q): (&[f32], &[f32]),
    solved: &[bool],
    (width, height): (usize, usize),
    wrap: bool,
    (max_iterations, tolerance): (usize, f64),
) -> MaskedSolve {
    let graph = Graph::new(width, height, solved, wrap);
    let b = graph.divergence(p, q);
    let inverse_degree = graph.inverse_degrees();
    // The iteration runs in f64: the smoothest error modes of a grid Laplacian have
    // eigenvalues near (pi / side)^2, so a residual small enough to pin them is below what
    // f32 sums resolve.
    let mut x: Vec<f64> = z.par_iter().map(|&v| v as f64).collect();
    let mut r = vec![0.0f64; x.len()];
    graph.apply(&x, &mut r);
    r.par_iter_mut().zip(&b).for_each(|(r, b)| *r = b - *r);
    let b_norm = dot(&b, &b).sqrt();
    drop(b);
    let mut s: Vec<f64> = r
        .par_iter()
        .zip(&inverse_degree)
        .map(|(r, m)| r * m)
        .collect();
    let mut d = s.clone();
    let mut rho = dot(&r, &s);
    let mut ad = vec![0.0f64; x.len()];
    let mut iterations = 0;
    let mut residual = dot(&r, &r).sqrt();
    while iterations < max_iterations && residual > tolerance * b_norm {
        let curvature = graph.apply(&d, &mut ad);
        if curvature <= 0.0 {
            break;
        }
        let alpha = rho / curvature;
        // One pass: step x and r, precondition r, and sum r.s and r.r.
        let (rho_next, rr) = x
            .par_chunks_mut(width)
            .zip(r.par_chunks_mut(width))
            .zip(s.par_chunks_mut(width))
            .zip(d.par_chunks(width).zip(ad.par_chunks(width)))
            .zip(inverse_degree.par_chunks(width))
            .map(|((((x, r), s), (d, ad)), m)| {
                let (mut rs, mut rr) = (0.0f64, 0.0f64);
                for i in 0..x.len() {
                    x[i] += alpha * d[i];
                    r[i] -= alpha * ad[i];
                    s[i] = r[i] * m[i];
                    rs += r[i] * s[i];
                    rr += r[i] * r[i];
                }
                (rs, rr)
            })
            .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
        let beta = rho_next / rho;
        rho = rho_next;
        d.par_iter_mut()
            .zip(&s)
            .for_each(|(d, s)| *d = s + beta * *d);
        residual = rr.sqrt();
        iterations += 1;
    }
    drop((r, s, d, ad));
    z.par_iter_mut().zip(&x).for_each(|(z, x)| *z = *x as f32);
    let pixels = solved.iter().filter(|&&s| s).count();
    let mean = z
        .iter()
        .zip(solved)
        .filter(|(_, &s)| s)
        .map(|(&v, _)| v as f64)
        .sum::<f64>()
        / pixels.max(1) as f64;
    z.par_iter_mut().zip(solved).for_each(|(v, &s)| {
        *v = if s { *v - mean as f32 } else { 0.0 };
    });
    MaskedSolve {
        pixels,
        iterations,
        relative_residual: if b_norm > 0.0 { residual / b_norm } else { 0.0 },
    }
}

/// `a . b`.
fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.par_iter().zip(b).map(|(a, b)| a * b).sum()
}
