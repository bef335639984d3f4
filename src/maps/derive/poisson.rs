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

/// Relative residual `|b - A z| / |b|` at which the iteration stops: the solved pixels'
/// slopes are then matched to a ten-thousandth of their own size, well below the noise of a
/// measured normal (a degree is 1.7 % of a slope).
const TOLERANCE: f64 = 1e-4;

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

/// The grid and which of its pixels take part: neighbours `i` and `j` are linked when both
/// are solved (across the left/right and top/bottom edges too when `wrap`).
struct Graph<'a> {
    width: usize,
    height: usize,
    solved: &'a [bool],
    wrap: bool,
}

impl Graph<'_> {
    /// The pixel right of `i` (column + 1) when the two are linked.
    fn right(&self, i: usize) -> Option<usize> {
        let c = i % self.width;
        let j = if c + 1 < self.width {
            i + 1
        } else if self.wrap && self.width > 1 {
            i + 1 - self.width
        } else {
            return None;
        };
        (self.solved[i] && self.solved[j]).then_some(j)
    }

    /// The pixel below `i` (row + 1) when the two are linked.
    fn below(&self, i: usize) -> Option<usize> {
        let n = self.width * self.height;
        let j = if i + self.width < n {
            i + self.width
        } else if self.wrap && self.height > 1 {
            i + self.width - n
        } else {
            return None;
        };
        (self.solved[i] && self.solved[j]).then_some(j)
    }

    /// The pixel left of `i`, when linked.
    fn left(&self, i: usize) -> Option<usize> {
        let c = i % self.width;
        let j = if c > 0 {
            i - 1
        } else if self.wrap && self.width > 1 {
            i + self.width - 1
        } else {
            return None;
        };
        (self.solved[i] && self.solved[j]).then_some(j)
    }

    /// The pixel above `i`, when linked.
    fn above(&self, i: usize) -> Option<usize> {
        let n = self.width * self.height;
        let j = if i >= self.width {
            i - self.width
        } else if self.wrap && self.height > 1 {
            i + n - self.width
        } else {
            return None;
        };
        (self.solved[i] && self.solved[j]).then_some(j)
    }

    /// `i`'s linked neighbours.
    fn neighbours(&self, i: usize) -> impl Iterator<Item = usize> + '_ {
        [self.left(i), self.right(i), self.above(i), self.below(i)]
            .into_iter()
            .flatten()
    }

    /// `(A z)_i = deg_i z_i - sum of z over i's neighbours`, into `out`.
    fn apply(&self, z: &[f32], out: &mut [f32]) {
        out.par_iter_mut().enumerate().for_each(|(i, o)| {
            let (mut degree, mut sum) = (0.0f32, 0.0f32);
            for j in self.neighbours(i) {
                degree += 1.0;
                sum += z[j];
            }
            *o = degree * z[i] - sum;
        });
    }

    /// The normal equations' right-hand side for slopes `p = dz/dcolumn`, `q = dz/drow`:
    /// each link's target difference is the mean of its two pixels' slopes along it, and
    /// `b_i` sums the targets of links arriving at `i` minus those leaving it.
    fn divergence(&self, p: &[f32], q: &[f32]) -> Vec<f32> {
        (0..p.len())
            .into_par_iter()
            .map(|i| {
                let mut b = 0.0f32;
                if let Some(j) = self.left(i) {
                    b += 0.5 * (p[i] + p[j]);
                }
                if let Some(j) = self.right(i) {
                    b -= 0.5 * (p[i] + p[j]);
                }
                if let Some(j) = self.above(i) {
                    b += 0.5 * (q[i] + q[j]);
                }
                if let Some(j) = self.below(i) {
                    b -= 0.5 * (q[i] + q[j]);
                }
                b
            })
            .collect()
    }

    /// `1 / deg_i` (0 for a pixel with no links: it takes no part in the solve).
    fn inverse_degrees(&self) -> Vec<f32> {
        (0..self.solved.len())
            .into_par_iter()
            .map(|i| {
                let degree = self.neighbours(i).count();
                if degree > 0 {
                    1.0 / degree as f32
                } else {
                    0.0
                }
            })
            .collect()
    }
}

/// Refines `z` (a starting surface, e.g. the Fourier solution of the same slopes) into the
/// least-squares surface over the `solved` pixels of a `width x height` grid, at most
/// `max_iterations` steps; pixels outside the mask end at 0 and the solved ones have zero
/// mean.
pub fn refine(
    z: &mut [f32],
    (p, q): (&[f32], &[f32]),
    solved: &[bool],
    (width, height): (usize, usize),
    wrap: bool,
    max_iterations: usize,
) -> MaskedSolve {
    let graph = Graph {
        width,
        height,
        solved,
        wrap,
    };
    let b = graph.divergence(p, q);
    let inverse_degree = graph.inverse_degrees();
    let mut r = vec![0.0f32; z.len()];
    graph.apply(z, &mut r);
    r.par_iter_mut().zip(&b).for_each(|(r, b)| *r = b - *r);
    let b_norm = dot(&b, &b).sqrt();
    let mut d = scaled(&r, &inverse_degree);
    let mut rho = dot(&r, &d);
    let mut ad = vec![0.0f32; z.len()];
    let mut iterations = 0;
    let mut residual = dot(&r, &r).sqrt();
    while iterations < max_iterations && residual > TOLERANCE * b_norm {
        graph.apply(&d, &mut ad);
        let curvature = dot(&d, &ad);
        if curvature <= 0.0 {
            break;
        }
        let alpha = (rho / curvature) as f32;
        z.par_iter_mut()
            .zip(r.par_iter_mut())
            .zip(d.par_iter().zip(&ad))
            .for_each(|((z, r), (d, ad))| {
                *z += alpha * d;
                *r -= alpha * ad;
            });
        let preconditioned = scaled(&r, &inverse_degree);
        let rho_next = dot(&r, &preconditioned);
        let beta = (rho_next / rho) as f32;
        rho = rho_next;
        d.par_iter_mut()
            .zip(&preconditioned)
            .for_each(|(d, s)| *d = s + beta * *d);
        residual = dot(&r, &r).sqrt();
        iterations += 1;
    }
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

/// `r_i m_i` for every pixel: the preconditioned residual.
fn scaled(r: &[f32], m: &[f32]) -> Vec<f32> {
    r.par_iter().zip(m).map(|(r, m)| r * m).collect()
}

/// `a . b`, summed in f64 (the residual falls four orders below the slopes' size).
fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.par_iter()
        .zip(b)
        .map(|(&a, &b)| a as f64 * b as f64)
        .sum()
}
