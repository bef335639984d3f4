//! Seamless tiling: the repeat is the user's, or the weave's period found as the strongest
//! repeat of the albedo's autocorrelation along the image axes (warp and weft run along
//! them on the scanner). A tile of one repeat is cut from the middle of the sample and its
//! first `blend` columns (then rows) are cross-faded with the pixels one repeat further on,
//! so the tile's last column is followed, across the wrap, by what really followed it.

use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use serde::Serialize;

use super::fft::Fft2;
use super::{SolvedMaps, TileChoice};
use crate::error::{Error, Result};
use crate::plane::Plane;

/// What tiling did, with the seam figures of the albedo's luminance.
#[derive(Clone, Debug, Serialize)]
pub struct TilingReport {
    /// The repeat in pixels as found (sub-pixel) or given, and as cut (whole pixels).
    pub period_px: [f64; 2],
    /// The tile's size in whole pixels, width then height (the period rounded, at least 2).
    pub tile_px: [usize; 2],
    /// Top-left corner of the tile in the source map.
    pub origin_px: [usize; 2],
    /// Width then height of the cross-fades, in pixels: a quarter of the tile, at least 1.
    pub blend_px: [usize; 2],
    /// Whether the period was found in the albedo (`TileChoice::Auto`) rather than given.
    pub found_from_albedo: bool,
    /// Mean luminance jump across the wrap beyond the mean jump between neighbours inside
    /// the tile: for the plain crop, and for the blended tile.
    pub seam_excess_crop: f64,
    /// The same figure for the blended tile.
    pub seam_excess_blended: f64,
}

/// Replaces `maps` with one seamless tile.
pub fn tile(maps: &mut SolvedMaps, choice: TileChoice) -> Result<TilingReport> {
    let (w, h) = (maps.width(), maps.height());
    let lum = luminance(&maps.albedo);
    let (period, found) = match choice {
        TileChoice::Auto => (weave_period(&lum)?, true),
        TileChoice::Repeat { width, height } => (
            [
                width.to_px(maps.pixel_mm, "the tile width")?,
                height.to_px(maps.pixel_mm, "the tile height")?,
            ],
            false,
        ),
    };
    let tile = period.map(|p| p.round().max(2.0) as usize);
    let blend = tile.map(|t| (t / 4).max(1));
    for (axis, (t, b, n)) in [(tile[0], blend[0], w), (tile[1], blend[1], h)]
        .into_iter()
        .enumerate()
    {
        if t + b > n {
            return Err(Error::Invalid(format!(
                "a tile of {t} px plus its {b} px blend does not fit the map's {n} px {}",
                ["width", "height"][axis]
            )));
        }
    }
    let origin = [(w - tile[0] - blend[0]) / 2, (h - tile[1] - blend[1]) / 2];
    let cut = Cut {
        origin,
        tile,
        blend,
    };
    let seam_excess_crop = seam_excess(&cut.crop(&lum));
    let tiled_lum = cut.blend(&lum);
    let seam_excess_blended = seam_excess(&tiled_lum);
    let normal = maps.normal.clone().map(|p| cut.blend(&p));
    maps.normal = renormalised(normal);
    maps.albedo = maps.albedo.clone().map(|p| cut.blend(&p));
    let solved = &maps.solved;
    maps.solved = (0..tile[0] * tile[1])
        .map(|i| solved[(origin[1] + i / tile[0]) * w + origin[0] + i % tile[0]])
        .collect();
    Ok(TilingReport {
        period_px: period,
        tile_px: tile,
        origin_px: origin,
        blend_px: blend,
        found_from_albedo: found,
        seam_excess_crop,
        seam_excess_blended,
    })
}

/// Where the tile is cut and how wide its blends are.
pub struct Cut {
    /// Top-left corner of the tile in the source map, in pixels (x, y).
    pub origin: [usize; 2],
    /// The tile's width and height in pixels.
    pub tile: [usize; 2],
    /// Widths in pixels of the blended leading columns and rows.
    pub blend: [usize; 2],
}

impl Cut {
    /// The plain crop, no blending.
    pub fn crop(&self, p: &Plane) -> Plane {
        let [x0, y0] = self.origin;
        let [tw, th] = self.tile;
        let data = (0..tw * th)
            .map(|i| p.data[(y0 + i / tw) * p.width + x0 + i % tw])
            .collect();
        Plane {
            width: tw,
            height: th,
            data,
        }
    }

    /// The tile with blended leading columns and rows.
    pub fn blend(&self, p: &Plane) -> Plane {
        let [x0, y0] = self.origin;
        let [tw, th] = self.tile;
        let [bw, bh] = self.blend;
        // Columns first, over every row the row blend will read.
        let rows = th + bh;
        let mut cols = vec![0.0f32; tw * rows];
        cols.par_chunks_mut(tw).enumerate().for_each(|(r, out)| {
            let src = &p.data[(y0 + r) * p.width..(y0 + r + 1) * p.width];
            for (x, v) in out.iter_mut().enumerate() {
                *v = fade(src[x0 + x], || src[x0 + x + tw], x, bw);
            }
        });
        let mut data = vec![0.0f32; tw * th];
        data.par_chunks_mut(tw).enumerate().for_each(|(y, out)| {
            for (x, v) in out.iter_mut().enumerate() {
                *v = fade(cols[y * tw + x], || cols[(y + th) * tw + x], y, bh);
            }
        });
        Plane {
            width: tw,
            height: th,
            data,
        }
    }
}

/// Inside the blend, from the pixel one repeat on (`next`, continuous with the tile's far
/// edge) to the pixel itself, with a smoothstep weight that is 0 at the edge.
fn fade(here: f32, next: impl Fn() -> f32, i: usize, blend: usize) -> f32 {
    if i >= blend {
        return here;
    }
    let next = next();
    let t = i as f32 / blend as f32;
    let s = t * t * (3.0 - 2.0 * t);
    s * here + (1.0 - s) * next
}

fn renormalised(mut n: [Plane; 3]) -> [Plane; 3] {
    for i in 0..n[0].len() {
        let v = [n[0].data[i], n[1].data[i], n[2].data[i]];
        let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-8);
        for c in 0..3 {
            n[c].data[i] = v[c] / len;
        }
    }
    n
}

/// Rec. 709 luminance of linear RGB.
pub fn luminance(rgb: &[Plane; 3]) -> Plane {
    let data = (0..rgb[0].len())
        .into_par_iter()
        .map(|i| 0.2126 * rgb[0].data[i] + 0.7152 * rgb[1].data[i] + 0.0722 * rgb[2].data[i])
        .collect();
    Plane {
        width: rgb[0].width,
        height: rgb[0].height,
        data,
    }
}

/// Mean jump across the wrap (last column to first, last row to first) minus the mean jump
/// between neighbours inside the tile, floored at zero: how much a seam stands out.
pub fn seam_excess(p: &Plane) -> f64 {
    let (w, h) = (p.width, p.height);
    let at = |x: usize, y: usize| p.data[y * w + x] as f64;
    let mut wrap = 0.0;
    let mut inside = 0.0;
    for y in 0..h {
        wrap += (at(w - 1, y) - at(0, y)).abs();
        inside += (1..w).map(|x| (at(x, y) - at(x - 1, y)).abs()).sum::<f64>() / (w - 1) as f64;
    }
    for x in 0..w {
        wrap += (at(x, h - 1) - at(x, 0)).abs();
        inside += (1..h).map(|y| (at(x, y) - at(x, y - 1)).abs()).sum::<f64>() / (h - 1) as f64;
    }
    ((wrap - inside) / (w + h) as f64).max(0.0)
}

/// The repeat of `lum` along x and y (pixels, sub-pixel): the autocorrelation (zero-padded,
/// normalised by the overlap) along each axis, past the central lobe its first peak within
/// 90 % of the strongest, refined at the farthest multiple of it that fits and divided back.
pub fn weave_period(lum: &Plane) -> Result<[f64; 2]> {
    let (w, h) = (lum.width, lum.height);
    if w < 16 || h < 16 {
        return Err(Error::Invalid(format!(
            "a {w} x {h} map is too small to find a weave period in"
        )));
    }
    let mean = lum.data.iter().map(|&v| v as f64).sum::<f64>() / lum.len() as f64;
    let (pw, ph) = (2 * w, 2 * h);
    let mut buf = vec![Complex32::default(); pw * ph];
    for y in 0..h {
        for x in 0..w {
            buf[y * pw + x] = Complex32::new(lum.data[y * w + x] - mean as f32, 0.0);
        }
    }
    let fft = Fft2::new(pw, ph);
    let mut spectrum = fft.forward(buf);
    spectrum
        .par_iter_mut()
        .for_each(|v| *v = Complex32::new(v.norm_sqr(), 0.0));
    let corr = fft.inverse(spectrum);
    let along_x: Vec<f64> = (0..w / 2)
        .map(|d| corr[d].re as f64 / ((w - d) * h) as f64)
        .collect();
    let along_y: Vec<f64> = (0..h / 2)
        .map(|d| corr[d * pw].re as f64 / ((h - d) * w) as f64)
        .collect();
    let px = period_1d(&along_x).ok_or_else(|| no_period("x"))?;
    let py = period_1d(&along_y).ok_or_else(|| no_period("y"))?;
    Ok([px, py])
}

fn no_period(axis: &str) -> Error {
    Error::Invalid(format!(
        "no repeat found along {axis} in the albedo (fewer than two periods in the map, or no \
         weave pattern): give the repeat with --tile WIDTHxHEIGHT"
    ))
}

/// The period of a 1-D autocorrelation `a` (lags 0..n).
fn period_1d(a: &[f64]) -> Option<f64> {
    let n = a.len();
    // Past the central lobe: its first local minimum.
    let start = (1..n - 1).find(|&d| a[d] <= a[d + 1])?;
    let peaks: Vec<usize> = (start.max(1)..n - 1)
        .filter(|&d| a[d] > a[d - 1] && a[d] >= a[d + 1] && a[d] > 0.0)
        .collect();
    let best = peaks
        .iter()
        .map(|&d| a[d])
        .fold(f64::NEG_INFINITY, f64::max);
    let first = *peaks.iter().find(|&&d| a[d] >= 0.9 * best)?;
    let rough = refine(a, first);
    // The farthest multiple that fits gives the finest estimate.
    let k = ((n - 2) as f64 / rough).floor().max(1.0);
    let guess = (k * rough).round() as usize;
    let lo = guess.saturating_sub(2).max(1);
    let hi = (guess + 2).min(n - 2);
    let at = (lo..=hi).max_by(|&i, &j| a[i].total_cmp(&a[j]))?;
    Some(refine(a, at) / k)
}

/// Sub-sample peak position from a parabola through the peak and its neighbours.
fn refine(a: &[f64], d: usize) -> f64 {
    if d == 0 || d + 1 >= a.len() {
        return d as f64;
    }
    let (l, c, r) = (a[d - 1], a[d], a[d + 1]);
    let denom = l - 2.0 * c + r;
    if denom.abs() < 1e-30 {
        d as f64
    } else {
        d as f64 + (0.5 * (l - r) / denom).clamp(-0.5, 0.5)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::textile::Textile;

    /// The synthetic twill's albedo with a short sett (red 4, cream 4 threads: the colour
    /// and the weave both repeat every 8 threads = 7.2 mm) at 0.07 mm per pixel, so the
    /// period is 102.857 px, not a whole number.
    fn weave(w: usize, h: usize) -> ([Plane; 3], f64) {
        let t = Textile {
            sett: vec![(0, 4), (3, 4)],
            fold_amplitude_m: 0.0,
            ..Textile::default()
        };
        let px = 0.07e-3;
        let mut rgb = [
            Plane::new(w, h, 0.0),
            Plane::new(w, h, 0.0),
            Plane::new(w, h, 0.0),
        ];
        for r in 0..h {
            for c in 0..w {
                let a = t.albedo(&t.surface_at(c as f64 * px, -(r as f64) * px));
                for k in 0..3 {
                    rgb[k].data[r * w + c] = a[k] as f32;
                }
            }
        }
        (rgb, 8.0 * t.thread_pitch_m / px)
    }

    #[test]
    fn the_weave_period_is_found_within_a_pixel() {
        let (rgb, period) = weave(640, 560);
        let found = weave_period(&luminance(&rgb)).unwrap();
        eprintln!("weave period: true {period:.3} px, found {found:?}");
        for p in found {
            assert!((p - period).abs() < 1.0, "found {p}, true {period}");
        }
    }

    #[test]
    fn blending_removes_the_seam_of_an_arbitrary_repeat() {
        // A repeat that is not the weave's: the plain crop has a seam, the blend hides it.
        let (rgb, _) = weave(400, 400);
        let lum = luminance(&rgb);
        let cut = Cut {
            origin: [37, 41],
            tile: [150, 170],
            blend: [37, 42],
        };
        let crop = seam_excess(&cut.crop(&lum));
        let blended = seam_excess(&cut.blend(&lum));
        eprintln!("seam excess: crop {crop:.5}, blended {blended:.5}");
        assert!(crop > 0.005, "the plain crop shows a seam: {crop}");
        assert!(
            blended <= 0.1 * crop,
            "seam reduced by {:.1} %",
            100.0 * (1.0 - blended / crop)
        );
    }

    #[test]
    fn too_small_maps_and_oversized_repeats_are_refused() {
        assert!(weave_period(&Plane::new(8, 8, 0.5)).is_err());
        let flat = Plane::new(64, 64, 0.5);
        let err = weave_period(&flat).unwrap_err().to_string();
        assert!(err.contains("--tile"), "{err}");
    }
}
