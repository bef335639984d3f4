//! The gray chart: a neutral value scale (such as the Munsell one in seed 004) photographed
//! under each light. From the raw CFA values of each patch: per-light white-balance gains
//! (the R and B multipliers that make the neutral patches neutral), and a linearity report
//! (fit of measured against nominal reflectance: slope, offset, R^2, the worst patch, and
//! the patches that clipped). Patch positions come from a chart description file plus the
//! chart's rectangle in the image, given by the user.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::plane::SensorWindow;
use crate::raw::Mosaic;
use crate::rig::Rig;

use crate::rig::{ChartDescription, ChartRect};
use crate::solve::NoiseModel;

/// One patch under one light: mean linear value per channel (1.0 = white level) of its CFA
/// samples, and whether any sample clipped.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct PatchReading {
    /// Mean linear value of the patch's R, G and B samples (1.0 = the white level); after
    /// [`calibrate`] with a [`Shading`], divided by the light's modelled shading at the patch.
    pub rgb: [f64; 3],
    /// Whether any of the patch's samples reached the white level.
    pub clipped: bool,
}

/// Linearity of one light's readings.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Linearity {
    /// Slope of the least-squares line of green reading against nominal reflectance (reading per
    /// unit reflectance).
    pub slope: f64,
    /// The line's value at zero reflectance: the reading a black patch would give (ideally 0).
    pub offset: f64,
    /// Coefficient of determination of the line over the unclipped patches (1: exactly linear).
    pub r_squared: f64,
    /// Index of the patch furthest from the fit, and its relative deviation.
    pub worst_patch: usize,
    /// Signed relative deviation of the worst patch from the line: (reading - line) / line.
    pub worst_deviation: f64,
    /// Patches left out because a sample clipped at the white level.
    pub clipped_patches: Vec<usize>,
}

/// One light's result.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LightChart {
    /// Multipliers for R, G, B that make the neutral patches neutral (G = 1).
    pub white_balance: [f64; 3],
    /// Linearity of the green channel against nominal reflectance.
    pub linearity: Linearity,
    /// Every patch's reading, in the chart's order (row by row from the top left).
    pub patches: Vec<PatchReading>,
}

/// The gray chart step's result (`graychart.toml`, and the `gray_chart` of a bundle): per light,
/// white balance and linearity.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ChartReport {
    /// The chart's name, from its description.
    pub chart: String,
    /// Per light, in LED order, its white balance, linearity and patch readings.
    pub lights: Vec<LightChart>,
}

/// Reads every patch of the chart in one light's mosaic.
pub fn read_patches(
    mosaic: &Mosaic,
    chart: &ChartDescription,
    rect: &ChartRect,
) -> Result<Vec<PatchReading>> {
    mosaic.validate()?;
    let (cw, ch) = (
        (rect.x1 - rect.x0) / chart.cols as f64,
        (rect.y1 - rect.y0) / chart.rows as f64,
    );
    let margin = 0.5 * (1.0 - chart.sample_fraction);
    let mut out = Vec::with_capacity(chart.rows * chart.cols);
    for r in 0..chart.rows {
        for c in 0..chart.cols {
            let x0 = (rect.x0 + (c as f64 + margin) * cw).round().max(0.0) as usize;
            let x1 = (rect.x0 + (c as f64 + 1.0 - margin) * cw).round() as usize;
            let y0 = (rect.y0 + (r as f64 + margin) * ch).round().max(0.0) as usize;
            let y1 = (rect.y0 + (r as f64 + 1.0 - margin) * ch).round() as usize;
            if x1 > mosaic.width || y1 > mosaic.height || x1 < x0 + 2 || y1 < y0 + 2 {
                return Err(Error::Invalid(format!(
                    "patch {} (row {r}, column {c}) at x {x0}..{x1}, y {y0}..{y1} is not inside the {}x{} image with at least 2x2 samples",
                    r * chart.cols + c,
                    mosaic.width,
                    mosaic.height
                )));
            }
            out.push(patch_mean(mosaic, x0, x1, y0, y1));
        }
    }
    Ok(out)
}

fn patch_mean(m: &Mosaic, x0: usize, x1: usize, y0: usize, y1: usize) -> PatchReading {
    let mut sum = [0.0f64; 3];
    let mut count = [0usize; 3];
    let mut clipped = false;
    for y in y0..y1 {
        for x in x0..x1 {
            let site = (y % 2, x % 2);
            let c = m.pattern[site.0][site.1] as usize;
            let raw = m.samples[y * m.width + x] as f32;
            clipped |= raw >= m.white;
            let black = m.black[site.0][site.1];
            sum[c] += ((raw - black) / (m.white - black)) as f64;
            count[c] += 1;
        }
    }
    PatchReading {
        rgb: std::array::from_fn(|c| sum[c] / count[c].max(1) as f64),
        clipped,
    }
}

/// White balance and linearity of one light from its patch readings.
pub fn analyse(chart: &ChartDescription, patches: Vec<PatchReading>) -> Result<LightChart> {
    let usable: Vec<usize> = (0..patches.len())
        .filter(|&i| !patches[i].clipped)
        .collect();
    if usable.len() < 3 {
        return Err(Error::Invalid(format!(
            "only {} unclipped patches: lower the exposure so at least 3 patches are below the white level",
            usable.len()
        )));
    }
    // Neutral patches: R/G and B/G are the same on all; weight by signal (least squares
    // through the origin of G against C).
    let gain = |c: usize| {
        let (num, den) = usable.iter().fold((0.0, 0.0), |(n, d), &i| {
            let p = &patches[i].rgb;
            (n + p[1] * p[c], d + p[c] * p[c])
        });
        num / den
    };
    let white_balance = [gain(0), 1.0, gain(2)];
    let x: Vec<f64> = usable.iter().map(|&i| chart.reflectance[i]).collect();
    let y: Vec<f64> = usable.iter().map(|&i| patches[i].rgb[1]).collect();
    let n = x.len() as f64;
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let sxx: f64 = x.iter().map(|v| (v - mx).powi(2)).sum();
    let sxy: f64 = x.iter().zip(&y).map(|(a, b)| (a - mx) * (b - my)).sum();
    let syy: f64 = y.iter().map(|v| (v - my).powi(2)).sum();
    let slope = sxy / sxx;
    let offset = my - slope * mx;
    let ss_res: f64 = x
        .iter()
        .zip(&y)
        .map(|(a, b)| (b - (offset + slope * a)).powi(2))
        .sum();
    let (worst_patch, worst_deviation) = usable
        .iter()
        .zip(x.iter().zip(&y))
        .map(|(&i, (a, b))| {
            let fit = offset + slope * a;
            (i, (b - fit) / fit)
        })
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
        .expect("at least three patches");
    Ok(LightChart {
        white_balance,
        linearity: Linearity {
            slope,
            offset,
            r_squared: 1.0 - ss_res / syy,
            worst_patch,
            worst_deviation,
            clipped_patches: (0..patches.len()).filter(|&i| patches[i].clipped).collect(),
        },
        patches,
    })
}

/// Where the mosaics are on the rig's sensor, so each patch's reading can be divided by its
/// light's shading there (inverse square, beam, incidence: across a 12 cm chart an LED at 30
/// degrees elevation varies by tens of percent, which would read as non-linearity).
pub struct Shading<'a> {
    /// The rig whose LEDs shade the chart (positions, beams, the camera that maps pixels to the
    /// table).
    pub rig: &'a Rig,
    /// Where the mosaics' pixels lie on the rig's sensor.
    pub window: SensorWindow,
}

impl Shading<'_> {
    /// Light `k`'s white-surface shading at the centre of each patch.
    fn at_patches(&self, k: usize, chart: &ChartDescription, rect: &ChartRect) -> Result<Vec<f64>> {
        let mapper = self.rig.camera.plane_mapper(self.rig.sample.z_m);
        let (cw, ch) = (
            (rect.x1 - rect.x0) / chart.cols as f64,
            (rect.y1 - rect.y0) / chart.rows as f64,
        );
        let mut out = Vec::new();
        for r in 0..chart.rows {
            for c in 0..chart.cols {
                let (u, v) = self.window.to_sensor(
                    rect.x0 + (c as f64 + 0.5) * cw,
                    rect.y0 + (r as f64 + 0.5) * ch,
                );
                let p = mapper
                    .map(u, v)
                    .ok_or_else(|| Error::Invalid("the chart is not on the table plane".into()))?;
                let s = self.rig.leds[k].sample_at(&p);
                out.push(s.falloff / self.rig.leds[k].power * s.direction.z.max(0.0));
            }
        }
        Ok(out)
    }
}

/// Reads and analyses the chart under every light; with `shading`, each reading is divided by
/// its light's modelled shading at the patch first.
pub fn calibrate(
    mosaics: &[Mosaic],
    chart: &ChartDescription,
    rect: &ChartRect,
    shading: Option<&Shading>,
) -> Result<ChartReport> {
    let lights = mosaics
        .iter()
        .enumerate()
        .map(|(k, m)| {
            let mut patches = read_patches(m, chart, rect)?;
            if let Some(s) = shading {
                for (p, shade) in patches.iter_mut().zip(s.at_patches(k, chart, rect)?) {
                    p.rgb = p.rgb.map(|v| v / shade);
                }
            }
            Ok(patches)
        })
        .map(|patches: Result<Vec<PatchReading>>| patches.and_then(|p| analyse(chart, p)))
        .enumerate()
        .map(|(k, r)| r.map_err(|e| Error::Invalid(format!("gray chart under light {k}: {e}"))))
        .collect::<Result<Vec<_>>>()?;
    Ok(ChartReport {
        chart: chart.name.clone(),
        lights,
    })
}

/// The chart's rectangle in the mosaics (`window` on the sensor): the projection of its world
/// corners through the calibrated camera.
pub fn chart_rect(rig: &Rig, window: SensorWindow, world: [f64; 4]) -> Result<ChartRect> {
    let [x0, x1, y0, y1] = world;
    let to_image = |x: f64, y: f64| -> Result<(f64, f64)> {
        let (u, v) = rig
            .camera
            .project(&nalgebra::Vector3::new(x, y, rig.sample.z_m))
            .ok_or_else(|| Error::Invalid("the gray chart is not in front of the camera".into()))?;
        Ok(((u - window.x0) / window.step, (v - window.y0) / window.step))
    };
    let (ax, ay) = to_image(x0, y1)?;
    let (bx, by) = to_image(x1, y0)?;
    Ok(ChartRect {
        x0: ax,
        y0: ay,
        x1: bx,
        y1: by,
    })
}

/// How far LED `k`'s modelled shading may bend the chart's linearity fit when the LED is up
/// to `error_m` from where `rig` puts it: for the LED moved by `error_m` along each axis,
/// ideal readings (nominal reflectance times the ratio of the moved LED's shading to the
/// modelled one at each patch) go through the same fit as the chart's readings, and the worst
/// patch's deviation is kept. A common factor goes into the slope; the spread shows, largest
/// on the darkest patch, where a small shift of the fitted offset is a large fraction.
pub(super) fn shading_uncertainty(
    rig: &Rig,
    k: usize,
    chart: &ChartDescription,
    rect: &ChartRect,
    window: SensorWindow,
    error_m: f64,
) -> Result<f64> {
    let mapper = rig.camera.plane_mapper(rig.sample.z_m);
    let (cw, ch) = (
        (rect.x1 - rect.x0) / chart.cols as f64,
        (rect.y1 - rect.y0) / chart.rows as f64,
    );
    let points = (0..chart.rows * chart.cols)
        .map(|i| {
            let (r, c) = (i / chart.cols, i % chart.cols);
            let (u, v) = window.to_sensor(
                rect.x0 + (c as f64 + 0.5) * cw,
                rect.y0 + (r as f64 + 0.5) * ch,
            );
            mapper
                .map(u, v)
                .ok_or_else(|| Error::Invalid("the gray chart is not on the table plane".into()))
        })
        .collect::<Result<Vec<_>>>()?;
    let shade = |led: &crate::rig::Led, p: &nalgebra::Vector3<f64>| {
        let s = led.sample_at(p);
        s.falloff * s.direction.z.max(0.0)
    };
    let led = &rig.leds[k];
    let mut worst = 0.0f64;
    for axis in 0..3 {
        for sign in [-1.0, 1.0] {
            let mut moved = led.clone();
            moved.position_m[axis] += sign * error_m;
            let readings = points
                .iter()
                .zip(&chart.reflectance)
                .map(|(p, x)| {
                    let y = x * shade(&moved, p) / shade(led, p);
                    PatchReading {
                        rgb: [y; 3],
                        clipped: false,
                    }
                })
                .collect();
            let fit = analyse(chart, readings)?;
            worst = worst.max(fit.linearity.worst_deviation.abs());
        }
    }
    Ok(worst)
}

/// The largest relative standard deviation of a patch's green mean: the sensor's noise at the
/// patch's level over the green samples the patch reading averages.
pub(super) fn patch_noise(
    mosaic: &Mosaic,
    chart: &ChartDescription,
    rect: &ChartRect,
    noise: &NoiseModel,
) -> Result<f64> {
    let side = |extent: f64, n: usize| extent / n as f64 * chart.sample_fraction;
    let samples = side(rect.x1 - rect.x0, chart.cols) * side(rect.y1 - rect.y0, chart.rows);
    // Half the CFA sites are green.
    let greens = (samples / 2.0).max(1.0);
    // The readings as the sensor gave them (before the shading is divided out).
    Ok(read_patches(mosaic, chart, rect)?
        .iter()
        .map(|p| {
            let v = p.rgb[1].max(1e-6);
            (noise.photon * v + noise.floor).sqrt() / greens.sqrt() / v
        })
        .fold(0.0, f64::max))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chart_descriptions_and_rectangles_are_checked() {
        assert!(ChartDescription::munsell_12().validate().is_ok());
        let mut bad = ChartDescription::munsell_12();
        bad.reflectance.pop();
        assert!(bad.validate().unwrap_err().1.contains("11 values"));
        assert!(ChartRect::parse("10,20,110,80").is_ok());
        assert!(ChartRect::parse("10,20,5,80")
            .unwrap_err()
            .to_string()
            .contains("X0,Y0,X1,Y1"));
    }
}
