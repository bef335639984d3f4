//! Finding the gray chart in its photographs when the user gives no rectangle. The chart lies
//! flat under a camera that looks straight down, its rows along the image rows and in the
//! order its description lists them, so it is an axis-aligned grid of `rows x cols` uniform
//! patches whose levels rise with the nominal reflectances. The search scores every grid
//! placement by how well it explains the image: the spread of the patch means that a line
//! through the nominal reflectances does not explain, plus the variance inside each patch,
//! over the spread of the patch means. Any placement that straddles patch edges or the
//! background scores worse. Coarse search on a 4-pixel lattice, then every pixel around the
//! best, on the CFA cells (2x2 samples) summed over all lights.

use crate::error::{Error, Needed, Result};
use crate::raw::Mosaic;
use crate::rig::{ChartDescription, ChartRect};

/// Summed-area tables of a cell image and of its squares.
struct Integral {
    w: usize,
    sum: Vec<f64>,
    sq: Vec<f64>,
}

impl Integral {
    fn new(values: &[f64], w: usize, h: usize) -> Self {
        let (mut sum, mut sq) = (vec![0.0; (w + 1) * (h + 1)], vec![0.0; (w + 1) * (h + 1)]);
        for y in 0..h {
            let (mut row, mut row_sq) = (0.0, 0.0);
            for x in 0..w {
                let v = values[y * w + x];
                row += v;
                row_sq += v * v;
                let i = (y + 1) * (w + 1) + x + 1;
                sum[i] = sum[i - (w + 1)] + row;
                sq[i] = sq[i - (w + 1)] + row_sq;
            }
        }
        Integral { w, sum, sq }
    }

    /// Mean and variance over `x0..x1`, `y0..y1`.
    fn stats(&self, x0: usize, y0: usize, x1: usize, y1: usize) -> (f64, f64) {
        let at = |t: &[f64], x: usize, y: usize| t[y * (self.w + 1) + x];
        let area = |t: &[f64]| at(t, x1, y1) - at(t, x0, y1) - at(t, x1, y0) + at(t, x0, y0);
        let n = ((x1 - x0) * (y1 - y0)) as f64;
        let mean = area(&self.sum) / n;
        (mean, (area(&self.sq) / n - mean * mean).max(0.0))
    }
}

/// The CFA cells' mean (black subtracted) summed over all lights: every light's shading
/// averages toward an even field, and the noise down.
fn cell_image(mosaics: &[Mosaic]) -> Result<(Vec<f64>, usize, usize)> {
    let first = mosaics
        .first()
        .ok_or_else(|| Error::Invalid("no gray-chart photographs".into()))?;
    let (w, h) = (first.width / 2, first.height / 2);
    let mut cells = vec![0.0; w * h];
    for m in mosaics {
        for y in 0..h {
            for x in 0..w {
                let mut s = 0.0;
                for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    let raw = m.samples[(2 * y + dy) * m.width + 2 * x + dx] as f64;
                    s += raw - m.black[dy][dx] as f64;
                }
                cells[y * w + x] += s / 4.0;
            }
        }
    }
    Ok((cells, w, h))
}

/// A grid placement in cells: origin and patch size.
#[derive(Clone, Copy, Debug)]
struct Grid {
    x0: usize,
    y0: usize,
    pw: usize,
    ph: usize,
}

/// Smallest patch side searched, in cells.
const MIN_PATCH: usize = 6;
/// Cells left out at each patch edge (lens blur).
const BLUR_CELLS: usize = 1;

fn score(t: &Integral, chart: &ChartDescription, g: Grid) -> f64 {
    // The whole patch but a cell of lens blur at its edges: a grid smaller than the chart's
    // would sample inside the right patches too, so evenness must hold out to the edges.
    let (mx, my) = (BLUR_CELLS, BLUR_CELLS);
    let n = chart.reflectance.len();
    let (mut means, mut within) = (Vec::with_capacity(n), 0.0);
    for r in 0..chart.rows {
        for c in 0..chart.cols {
            let (x, y) = (g.x0 + c * g.pw, g.y0 + r * g.ph);
            let (m, v) = t.stats(x + mx, y + my, x + g.pw - mx, y + g.ph - my);
            means.push(m);
            within += v;
        }
    }
    let nf = n as f64;
    let (sx, sy) = (
        chart.reflectance.iter().sum::<f64>() / nf,
        means.iter().sum::<f64>() / nf,
    );
    let sxx: f64 = chart.reflectance.iter().map(|x| (x - sx).powi(2)).sum();
    let sxy: f64 = chart
        .reflectance
        .iter()
        .zip(&means)
        .map(|(x, y)| (x - sx) * (y - sy))
        .sum();
    let syy: f64 = means.iter().map(|y| (y - sy).powi(2)).sum();
    if sxy <= 0.0 || syy <= 0.0 {
        return f64::INFINITY;
    }
    let unexplained = syy - sxy * sxy / sxx;
    (unexplained + within) / syy
}

/// The chart's rectangle in image pixels, found in its photographs (module docs).
pub fn find(mosaics: &[Mosaic], chart: &ChartDescription) -> Result<ChartRect> {
    let (cells, w, h) = cell_image(mosaics)?;
    let t = Integral::new(&cells, w, h);
    let (rows, cols) = (chart.rows, chart.cols);
    let (max_pw, max_ph) = (w / cols, h / rows);
    if max_pw < MIN_PATCH || max_ph < MIN_PATCH {
        return Err(Error::NeedsValue(Needed::ChartRect {
            reason: format!(
                "the photographs ({}x{}) are too small to find a {rows}x{cols} chart in",
                2 * w,
                2 * h
            ),
        }));
    }
    // Every placement's score; then the largest grid among those that explain the image about
    // as well as the best one (a grid inside the chart's would score as well as the chart's).
    let fits = |g: &Grid| g.x0 + cols * g.pw <= w && g.y0 + rows * g.ph <= h;
    let pick = |candidates: Vec<Grid>| -> Option<(f64, Grid)> {
        let scored: Vec<(f64, Grid)> = candidates
            .into_iter()
            .filter(fits)
            .map(|g| (score(&t, chart, g), g))
            .collect();
        let best = scored.iter().map(|c| c.0).fold(f64::INFINITY, f64::min);
        let limit = 2.0 * best + 1e-3;
        scored
            .into_iter()
            .filter(|c| c.0 <= limit)
            .max_by_key(|c| c.1.pw * c.1.ph)
    };
    let step = 4;
    let mut coarse = Vec::new();
    for pw in (MIN_PATCH..=max_pw).step_by(step) {
        for ph in (MIN_PATCH..=max_ph).step_by(step) {
            for y0 in (0..=h - rows * ph).step_by(step) {
                for x0 in (0..=w - cols * pw).step_by(step) {
                    coarse.push(Grid { x0, y0, pw, ph });
                }
            }
        }
    }
    let (_, c) = pick(coarse).ok_or_else(|| {
        Error::NeedsValue(Needed::ChartRect {
            reason: "the gray chart was not found in the photographs".into(),
        })
    })?;
    let around = |v: usize, lo: usize| v.saturating_sub(step).max(lo)..=v + step;
    let mut fine = Vec::new();
    for pw in around(c.pw, MIN_PATCH) {
        for ph in around(c.ph, MIN_PATCH) {
            for y0 in around(c.y0, 0) {
                for x0 in around(c.x0, 0) {
                    fine.push(Grid { x0, y0, pw, ph });
                }
            }
        }
    }
    let (s, g) = pick(fine).expect("the coarse grid is among them");
    // At the chart, the patch means follow the reflectances and the patches are even: the
    // score is far below 1. Around 1, nothing in the image looks like the chart.
    if s > 0.25 {
        return Err(Error::NeedsValue(Needed::ChartRect {
            reason: format!(
                "no {rows}x{cols} chart with levels rising as its description's reflectances \
                 was found (best fit leaves {:.0} % of the patch spread unexplained): check the \
                 chart lies with its first row at the top of the image",
                100.0 * s
            ),
        }));
    }
    Ok(ChartRect {
        x0: (2 * g.x0) as f64,
        y0: (2 * g.y0) as f64,
        x1: (2 * (g.x0 + cols * g.pw)) as f64,
        y1: (2 * (g.y0 + rows * g.ph)) as f64,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_even_field_holds_no_chart() {
        let even = Mosaic {
            width: 256,
            height: 128,
            pattern: [[0, 1], [1, 2]],
            black: [[512.0; 2]; 2],
            white: 16383.0,
            samples: (0..256 * 128)
                .map(|i| 3000 + (i * 7919 % 13) as u16)
                .collect(),
        };
        let err = find(&[even], &ChartDescription::munsell_12()).unwrap_err();
        assert!(
            matches!(err, Error::NeedsValue(Needed::ChartRect { .. })),
            "{err}"
        );
    }
}
