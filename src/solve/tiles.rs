//! Per-pixel light coefficients for the streaming kernel, exact or interpolated across tiles.
//!
//! A pixel's near-light least-squares problem needs, per light `k`, the unit direction `l_k`
//! from the pixel's point on the sample toward the LED and the inverse of the LED's falloff
//! there (`1 / falloff_k`, which turns a raw value into `I'`). Both change slowly across the
//! sample (the LEDs are ~0.5 m away), so they are computed exactly at the corners of square
//! tiles and interpolated bilinearly in between. The tile size is the largest whose
//! interpolation error, measured at the tiles' centres and edge midpoints on test normals,
//! stays within the tolerance; the error is kept in [`TileGrid::estimated_max_error_deg`].
//!
//! Layout of one point's coefficients: `3 * lights` direction components, then `lights`
//! inverse falloffs, then the six entries (xx, xy, xz, yy, yz, zz) of `sum_k l_k l_k^T` over
//! all lights (the kernel subtracts the lights a pixel drops).

use nalgebra::{Matrix3, Vector3};

use super::lanes::{madd, Real, LANES};
use super::lights::Illumination;
use crate::math::angle_deg;

/// Tile sizes tried, largest first. A chunk of the kernel's 16 lanes inside one tile
/// interpolates from one node column; one that crosses a tile border fills a per-lane table,
/// which every chunk does below 16 px tiles (still far cheaper than exact coefficients per
/// pixel; small images, where a pixel covers much of the sensor, need small tiles).
pub const TILE_SIZES: [usize; 7] = [256, 128, 64, 32, 16, 8, 4];

/// The exact coefficients at one point (layout above). `false` where the pixel's ray misses
/// the sample or a light gives no light there.
pub fn exact_coefficients(illumination: &Illumination, x: f64, y: f64, out: &mut [f64]) -> bool {
    let Some(point) = illumination.point_at(x, y) else {
        return false;
    };
    let k_count = illumination.len();
    let mut a = [0.0; 6];
    for k in 0..k_count {
        let s = illumination.sample(k, &point);
        if !(s.falloff > 0.0 && s.falloff.is_finite()) {
            return false;
        }
        let l = s.direction;
        out[3 * k..3 * k + 3].copy_from_slice(l.as_slice());
        out[3 * k_count + k] = 1.0 / s.falloff;
        for (e, v) in a.iter_mut().zip([
            l.x * l.x,
            l.x * l.y,
            l.x * l.z,
            l.y * l.y,
            l.y * l.z,
            l.z * l.z,
        ]) {
            *e += v;
        }
    }
    out[4 * k_count..4 * k_count + 6].copy_from_slice(&a);
    true
}

/// Values per point for `lights` lights.
pub fn stride(lights: usize) -> usize {
    4 * lights + 6
}

/// Least-squares normal from coefficients `c` (layout above) and raw measurements `raw` (in
/// falloff units; `None`: light not used): `(sum l l^T)^-1 sum l raw / falloff`.
fn solve_with(c: &[f64], raw: &[Option<f64>]) -> Option<Vector3<f64>> {
    let k_count = raw.len();
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for (k, r) in raw.iter().enumerate() {
        let Some(r) = r else { continue };
        let l = Vector3::new(c[3 * k], c[3 * k + 1], c[3 * k + 2]);
        a += l * l.transpose();
        b += l * (r * c[3 * k_count + k]);
    }
    Some(a.try_inverse()? * b)
}

/// Exact coefficients at the corners of `tile x tile` pixel tiles.
pub struct TileGrid {
    /// Tile side, in pixels.
    pub tile: usize,
    /// Node columns: at pixel columns `min(j * tile, width - 1)`.
    pub nodes_x: usize,
    /// Node rows: at pixel rows `min(j * tile, height - 1)`.
    pub nodes_y: usize,
    /// Values per node: [`stride`].
    pub stride: usize,
    /// `nodes_y * nodes_x * stride` coefficients.
    pub values: Vec<f64>,
    /// Whether each node could be solved from all lights.
    pub node_ok: Vec<bool>,
    /// Largest normal error the interpolation caused on the test normals (degrees).
    pub estimated_max_error_deg: f64,
}

impl TileGrid {
    /// Interpolates the node coefficients to row `y` of a `w x h` image: the value at each
    /// node column (`row_left`) and the slope toward the next one (`row_slope`).
    #[inline(always)]
    pub(super) fn interpolate_row<T: Real>(
        &self,
        y: usize,
        (w, h): (usize, usize),
        row_left: &mut [T],
        row_slope: &mut [T],
    ) {
        let grid = self;
        let (jy, ty) = grid.locate(y, h, grid.nodes_y);
        let jy1 = (jy + 1).min(grid.nodes_y - 1);
        let stride = grid.stride;
        // Iterators, not indices: the loops vectorise (indexed, the second ran scalar).
        for (jx, left) in row_left.chunks_exact_mut(stride).enumerate() {
            let (a, c) = (grid.node(jx, jy), grid.node(jx, jy1));
            for ((o, &a), &c) in left.iter_mut().zip(a).zip(c) {
                *o = T::of(a + (c - a) * ty);
            }
        }
        let left = &*row_left;
        for (jx, slope) in row_slope.chunks_exact_mut(stride).enumerate() {
            let jx1 = (jx + 1).min(grid.nodes_x - 1);
            let span = grid.node_pos(jx1, w) as f64 - grid.node_pos(jx, w) as f64;
            let inv = T::of(if span > 0.0 { 1.0 / span } else { 0.0 });
            let this = &left[jx * stride..(jx + 1) * stride];
            let next = &left[jx1 * stride..(jx1 + 1) * stride];
            for ((o, &a), &b) in slope.iter_mut().zip(this).zip(next) {
                *o = (b - a) * inv;
            }
        }
    }

    /// Pixel position of node `j` along an axis of `size` pixels.
    #[inline]
    pub fn node_pos(&self, j: usize, size: usize) -> usize {
        (j * self.tile).min(size.saturating_sub(1))
    }

    fn build(illumination: &Illumination, w: usize, h: usize, tile: usize) -> Self {
        let count = |size: usize| (size.saturating_sub(1)).div_ceil(tile) + 1;
        let (nodes_x, nodes_y) = (count(w), count(h));
        let stride = stride(illumination.len());
        let mut values = vec![0.0; nodes_x * nodes_y * stride];
        let mut node_ok = vec![false; nodes_x * nodes_y];
        for (n, (chunk, ok)) in values.chunks_mut(stride).zip(&mut node_ok).enumerate() {
            let x = (n % nodes_x * tile).min(w - 1) as f64;
            let y = (n / nodes_x * tile).min(h - 1) as f64;
            *ok = exact_coefficients(illumination, x, y, chunk);
        }
        TileGrid {
            tile,
            nodes_x,
            nodes_y,
            stride,
            values,
            node_ok,
            estimated_max_error_deg: 0.0,
        }
    }

    /// The node coefficients at node `(jx, jy)`.
    #[inline]
    pub fn node(&self, jx: usize, jy: usize) -> &[f64] {
        let n = jy * self.nodes_x + jx;
        &self.values[n * self.stride..(n + 1) * self.stride]
    }

    /// Whether the tile whose top-left node is `(jx, jy)` has all four corners solvable.
    #[inline]
    pub fn tile_ok(&self, jx: usize, jy: usize) -> bool {
        let jx1 = (jx + 1).min(self.nodes_x - 1);
        let jy1 = (jy + 1).min(self.nodes_y - 1);
        [(jx, jy), (jx1, jy), (jx, jy1), (jx1, jy1)]
            .iter()
            .all(|&(a, b)| self.node_ok[b * self.nodes_x + a])
    }

    /// Node index below `p` along an axis with `nodes` nodes, and the fraction toward the next.
    #[inline]
    pub fn locate(&self, p: usize, size: usize, nodes: usize) -> (usize, f64) {
        if nodes < 2 {
            return (0, 0.0);
        }
        let j = (p / self.tile).min(nodes - 2);
        let (p0, p1) = (self.node_pos(j, size), self.node_pos(j + 1, size));
        let t = if p1 > p0 {
            (p - p0) as f64 / (p1 - p0) as f64
        } else {
            0.0
        };
        (j, t)
    }

    /// Bilinear interpolation of the node coefficients at pixel `(x, y)` into `out`.
    pub fn interpolate(&self, x: usize, y: usize, w: usize, h: usize, out: &mut [f64]) -> bool {
        let (jx, tx) = self.locate(x, w, self.nodes_x);
        let (jy, ty) = self.locate(y, h, self.nodes_y);
        if !self.tile_ok(jx, jy) {
            return false;
        }
        let jx1 = (jx + 1).min(self.nodes_x - 1);
        let jy1 = (jy + 1).min(self.nodes_y - 1);
        let (a, b) = (self.node(jx, jy), self.node(jx1, jy));
        let (c, d) = (self.node(jx, jy1), self.node(jx1, jy1));
        for i in 0..self.stride {
            let top = a[i] + (b[i] - a[i]) * tx;
            let bottom = c[i] + (d[i] - c[i]) * tx;
            out[i] = top + (bottom - top) * ty;
        }
        true
    }
}

/// Test normals: straight up, and tilted 25, 50 and 65 degrees four ways each (the steep ones
/// lose lights to attached shadow, where interpolation errors are amplified most).
fn test_normals() -> Vec<Vector3<f64>> {
    let mut normals = vec![Vector3::z()];
    for tilt in [25f64, 50.0, 65.0] {
        let (s, c) = tilt.to_radians().sin_cos();
        normals.extend([
            Vector3::new(s, 0.0, c),
            Vector3::new(-s, 0.0, c),
            Vector3::new(0.0, s, c),
            Vector3::new(0.0, -s, c),
        ]);
    }
    normals
}

/// The planner aims at this fraction of the tolerance: the test normals sample the error,
/// they do not bound it (a real pixel's normal and dropped lights differ).
const SAFETY: f64 = 0.5;

/// Largest normal error (degrees) interpolated coefficients cause at pixel `(x, y)`: noise-free
/// measurements `falloff_k (n . l_k)` of each test normal that every light sees are solved with
/// the interpolated coefficients and compared with `n` (exact coefficients reproduce `n`).
fn interpolation_error_at(
    grid: &TileGrid,
    illumination: &Illumination,
    (x, y, w, h): (usize, usize, usize, usize),
    scratch: &mut [f64],
) -> Option<f64> {
    if !grid.interpolate(x, y, w, h, scratch) {
        return None;
    }
    let point = illumination.point_at(x as f64, y as f64)?;
    let samples: Vec<_> = (0..illumination.len())
        .map(|k| illumination.sample(k, &point))
        .collect();
    let mut worst: Option<f64> = None;
    for n in test_normals() {
        // As the solver does, lights the surface faces away from (attached shadow) are dropped.
        let raw: Vec<Option<f64>> = samples
            .iter()
            .map(|s| {
                let cos = n.dot(&s.direction);
                (cos > 0.05).then_some(s.falloff * cos)
            })
            .collect();
        if raw.iter().flatten().count() < 3 {
            continue;
        }
        let e = angle_deg(&solve_with(scratch, &raw)?, &n);
        worst = Some(worst.map_or(e, |w: f64| w.max(e)));
    }
    worst
}

/// The largest tile whose interpolation error stays within half of `tolerance_deg`, checked at the
/// centre and edge midpoints of every tile (at most ~400 tiles are sampled, evenly). `None`
/// when even the smallest tile exceeds the tolerance (the caller then computes `G` per pixel).
pub fn plan(
    illumination: &Illumination,
    w: usize,
    h: usize,
    tolerance_deg: f64,
) -> Option<TileGrid> {
    let mut scratch = vec![0.0; stride(illumination.len())];
    for tile in TILE_SIZES {
        let mut grid = TileGrid::build(illumination, w, h, tile);
        let tiles = (grid.nodes_x.max(2) - 1) * (grid.nodes_y.max(2) - 1);
        let step = (tiles / 400).max(1);
        let mut worst: f64 = 0.0;
        for t in (0..tiles).step_by(step) {
            let (tx, ty) = (t % (grid.nodes_x.max(2) - 1), t / (grid.nodes_x.max(2) - 1));
            let x0 = grid.node_pos(tx, w);
            let y0 = grid.node_pos(ty, h);
            let x1 = grid.node_pos(tx + 1, w);
            let y1 = grid.node_pos(ty + 1, h);
            let (xm, ym) = ((x0 + x1) / 2, (y0 + y1) / 2);
            for (x, y) in [(xm, ym), (xm, y0), (x0, ym)] {
                if let Some(e) =
                    interpolation_error_at(&grid, illumination, (x, y, w, h), &mut scratch)
                {
                    worst = worst.max(e);
                }
            }
        }
        if worst <= tolerance_deg * SAFETY {
            grid.estimated_max_error_deg = worst;
            return Some(grid);
        }
    }
    None
}

/// Where a chunk's coefficients come from: a straight line along the row (the chunk lies in
/// one tile: each value is `left + slope * offset`, computed where it is used), or a table.
pub(super) enum Source<'a, T> {
    /// Node values and slopes along the row, and each lane's offset from the node column.
    Linear {
        /// The node column's coefficients at this row.
        left: &'a [T],
        /// Their change per pixel toward the next node column.
        slope: &'a [T],
        /// Each lane's column minus the node column.
        offset: [T; LANES],
    },
    /// Per coefficient, one value per lane.
    Table(&'a [[T; LANES]]),
}

impl<T: Real> Source<'_, T> {
    /// Coefficient `i` for every lane.
    #[inline(always)]
    pub(super) fn get<const FMA: bool>(&self, i: usize) -> [T; LANES] {
        match self {
            Source::Linear {
                left,
                slope,
                offset,
            } => {
                let (a, b) = (left[i], slope[i]);
                let mut out = *offset;
                for o in &mut out {
                    *o = madd::<T, FMA>(b, *o, a);
                }
                out
            }
            Source::Table(t) => t[i],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plane::SensorWindow;
    use crate::rig::Rig;
    use crate::solve::{LightModel, LightSource};

    /// A small image of the whole field (a pixel spans 16 sensor pixels) needs tiles under 16
    /// px to stay within a 0.01-degree tolerance; it gets them instead of exact coefficients per
    /// pixel, and the interpolation error measured at pixels between the nodes stays within
    /// the tolerance.
    #[test]
    fn small_whole_field_images_get_small_tiles_within_the_tolerance() {
        let rig = Rig::default_rig();
        let (w, h) = (308, 204);
        let window = SensorWindow::centred(
            rig.camera.width as usize,
            rig.camera.height as usize,
            w,
            h,
            16.0,
        );
        let illumination =
            Illumination::new(&LightSource::Rig(&rig), LightModel::Near, w, h, window).unwrap();
        let tolerance = 0.01;
        let grid = plan(&illumination, w, h, tolerance).expect("a tile grid");
        assert!(grid.tile < 16, "{} px tiles", grid.tile);
        let mut scratch = vec![0.0; stride(illumination.len())];
        let mut worst: f64 = 0.0;
        for y in (1..h).step_by(7) {
            for x in (1..w).step_by(5) {
                if let Some(e) =
                    interpolation_error_at(&grid, &illumination, (x, y, w, h), &mut scratch)
                {
                    worst = worst.max(e);
                }
            }
        }
        assert!(worst > 0.0 && worst <= tolerance, "{worst}");
    }
}
