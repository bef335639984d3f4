//! Renders the textile as the rig's camera sees it under each LED, with exact per-pixel
//! ground truth. The geometry is the same the solver uses: each pixel's ray meets the sample's
//! mean plane, the LED is a point source with inverse-square falloff and a `cos^m` beam, the
//! relief only enters through the normal (and through cast shadows when asked for).

use nalgebra::Vector3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::brdf::{lambert, sheen_shade, Sheen};
use super::textile::Textile;
use crate::error::{Error, Result};
use crate::plane::{Frames, LightFrame, Plane, RgbPlanes, SensorWindow};
use crate::progress::Progress;
use crate::rig::Rig;

/// Which effects beyond Lambertian shading to render.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneOptions {
    /// Cast shadows from the height field.
    pub shadows: bool,
    /// Light still reaching a point in cast shadow, as a fraction of the direct light
    /// (interreflection between threads); only with `shadows`.
    pub shadow_fill: f64,
    /// The cloth sheen lobe of seed eq. 23; `None` renders Lambertian.
    pub sheen: Option<Sheen>,
}

/// Exact per-pixel truth of what was rendered.
#[derive(Clone, Debug)]
pub struct GroundTruth {
    /// Unit normals in the world frame.
    pub normal: [Plane; 3],
    /// Linear diffuse albedo.
    pub albedo: [Plane; 3],
    /// Height above the sample's mean plane (m).
    pub height: Plane,
}

/// The textile placed under the rig, sampled at the frames' pixels.
pub struct Scene<'a> {
    rig: &'a Rig,
    textile: Textile,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Where the image's pixels sit on the rig's sensor.
    pub window: SensorWindow,
    options: SceneOptions,
    /// The exact normal, albedo and height at every pixel.
    pub truth: GroundTruth,
    /// World point on the mean plane seen by each pixel (x, y only; z is the plane).
    points: Vec<[f64; 2]>,
    shadow_grid: Option<HeightGrid>,
}

impl<'a> Scene<'a> {
    /// Samples the textile at every pixel of a `width x height` window of the rig's sensor.
    pub fn build(
        rig: &'a Rig,
        textile: Textile,
        width: usize,
        height: usize,
        window: SensorWindow,
        options: SceneOptions,
        progress: &dyn Progress,
    ) -> Result<Scene<'a>> {
        if width == 0 || height == 0 {
            return Err(Error::Invalid(
                "the synthetic image must be at least 1x1".into(),
            ));
        }
        let mapper = rig.camera.plane_mapper(rig.sample.z_m);
        let n = width * height;
        let mut points = vec![[0.0; 2]; n];
        let mut truth = GroundTruth {
            normal: std::array::from_fn(|_| Plane::new(width, height, 0.0)),
            albedo: std::array::from_fn(|_| Plane::new(width, height, 0.0)),
            height: Plane::new(width, height, 0.0),
        };
        progress.begin("scene", height as u64);
        let missed = std::sync::atomic::AtomicBool::new(false);
        {
            let [nx, ny, nz] = &mut truth.normal;
            let [ar, ag, ab] = &mut truth.albedo;
            points
                .par_chunks_mut(width)
                .zip(nx.data.par_chunks_mut(width))
                .zip(ny.data.par_chunks_mut(width))
                .zip(nz.data.par_chunks_mut(width))
                .zip(ar.data.par_chunks_mut(width))
                .zip(ag.data.par_chunks_mut(width))
                .zip(ab.data.par_chunks_mut(width))
                .zip(truth.height.data.par_chunks_mut(width))
                .enumerate()
                .for_each(|(y, (((((((pts, nx), ny), nz), ar), ag), ab), hh))| {
                    for x in 0..width {
                        let (u, v) = window.to_sensor(x as f64, y as f64);
                        let Some(p) = mapper.map(u, v) else {
                            missed.store(true, std::sync::atomic::Ordering::Relaxed);
                            continue;
                        };
                        pts[x] = [p.x, p.y];
                        let surface = textile.surface_at(p.x, p.y);
                        let normal = textile.normal_at(p.x, p.y);
                        let albedo = textile.albedo(&surface);
                        nx[x] = normal[0] as f32;
                        ny[x] = normal[1] as f32;
                        nz[x] = normal[2] as f32;
                        ar[x] = albedo[0] as f32;
                        ag[x] = albedo[1] as f32;
                        ab[x] = albedo[2] as f32;
                        hh[x] = surface.height as f32;
                    }
                    progress.advance(1);
                });
        }
        progress.end();
        if missed.into_inner() {
            return Err(Error::Invalid(
                "part of the synthetic window does not see the sample plane".into(),
            ));
        }
        let shadow_grid = options
            .shadows
            .then(|| HeightGrid::build(&textile, &points, rig, window));
        Ok(Scene {
            rig,
            textile,
            width,
            height,
            window,
            options,
            truth,
            points,
            shadow_grid,
        })
    }

    /// The textile the scene samples.
    pub fn textile(&self) -> &Textile {
        &self.textile
    }

    /// The linear image under LED `k` (1.0 = white level), before the sensor: no noise, no
    /// clipping. `exposure` scales it relative to the rig's calibration exposure.
    pub fn render_light(&self, k: usize, exposure: f64) -> RgbPlanes {
        let rig = self.rig;
        let led = &rig.leds[k];
        let rgb_power = rig.led_rgb_power(k);
        let scale = rgb_power.map(|c| c / led.power * exposure);
        let camera = rig.camera.centre();
        let plane_z = rig.sample.z_m;
        let width = self.width;
        let mut out = RgbPlanes::new(width, self.height);
        out.par_rows_mut(|y, rows| {
            for x in 0..width {
                let i = y * width + x;
                let [px, py] = self.points[i];
                let point = Vector3::new(px, py, plane_z);
                let light = led.sample_at(&point);
                let n = self.truth_normal(i);
                let kd: [f64; 3] = std::array::from_fn(|c| self.truth.albedo[c].data[i] as f64);
                let shade = match &self.options.sheen {
                    None => lambert(kd, &n, &light.direction),
                    Some(sheen) => {
                        let view = (camera - point).normalize();
                        sheen_shade(sheen, kd, &n, &light.direction, &view)
                    }
                };
                let visibility = match &self.shadow_grid {
                    Some(grid)
                        if grid.shadowed(
                            px,
                            py,
                            self.truth.height.data[i] as f64,
                            &led.position(),
                        ) =>
                    {
                        self.options.shadow_fill
                    }
                    _ => 1.0,
                };
                for c in 0..3 {
                    rows[c][x] = (light.falloff * scale[c] * shade[c] * visibility) as f32;
                }
            }
        });
        out
    }

    /// All lights, noise-free and unclipped (an ideal sensor).
    pub fn render_ideal(&self, exposure: f64, progress: &dyn Progress) -> Frames {
        progress.begin("render", self.rig.leds.len() as u64);
        let lights = (0..self.rig.leds.len())
            .map(|k| {
                let rgb = self.render_light(k, exposure);
                progress.advance(1);
                LightFrame {
                    rgb,
                    saturated: None,
                    cfa: None,
                    dn: None,
                    cfa_dn: None,
                }
            })
            .collect();
        progress.end();
        Frames {
            width: self.width,
            height: self.height,
            window: self.window,
            lights,
        }
    }

    fn truth_normal(&self, i: usize) -> Vector3<f64> {
        Vector3::new(
            self.truth.normal[0].data[i] as f64,
            self.truth.normal[1].data[i] as f64,
            self.truth.normal[2].data[i] as f64,
        )
    }
}

/// Samples a shadow grid may hold to resolve the threads at a coarse step (4 bytes each).
const MAX_RELIEF_GRID_CELLS: f64 = 16e6;

/// Side of the shadow grid's cells for pixels `footprint` apart on the table, threads
/// `thread_pitch` apart, over `area` (m^2). Half the footprint keeps fibre-scale shadows at
/// full resolution. At a coarse `--step` the footprint outgrows the threads, and a grid that
/// coarse smooths away the relief that casts the shadows (at step 16 nothing was shadowed):
/// there the cell is a sixteenth of the pitch, or as fine as `MAX_RELIEF_GRID_CELLS` allows
/// over the whole field (a tenth of the pitch over the default rig's full sensor).
fn shadow_grid_cell(footprint: f64, thread_pitch: f64, area: f64) -> f64 {
    let relief = (thread_pitch / 16.0).max((area / MAX_RELIEF_GRID_CELLS).sqrt());
    (0.5 * footprint).min(relief).max(1e-6)
}

/// The height field resampled on a regular world grid around the visible sample, for
/// marching shadow rays toward each LED.
struct HeightGrid {
    x0: f64,
    y0: f64,
    cell: f64,
    nx: usize,
    ny: usize,
    heights: Vec<f32>,
    max_height: f64,
}

impl HeightGrid {
    fn build(textile: &Textile, points: &[[f64; 2]], rig: &Rig, window: SensorWindow) -> Self {
        let (mut xmin, mut xmax, mut ymin, mut ymax) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for p in points {
            xmin = xmin.min(p[0]);
            xmax = xmax.max(p[0]);
            ymin = ymin.min(p[1]);
            ymax = ymax.max(p[1]);
        }
        // A shadow can only come from relief within (height range) / tan(lowest elevation).
        let lowest_elevation = rig
            .leds
            .iter()
            .map(|l| (l.position_m[2] / l.position_m[0].hypot(l.position_m[1])).atan())
            .fold(f64::MAX, f64::min)
            .max(5f64.to_radians());
        let margin = (textile.max_height() - textile.min_height()) / lowest_elevation.tan() + 1e-3;
        let footprint = window.step * (rig.camera.position_m[2] - rig.sample.z_m) / rig.camera.fx;
        let cell = shadow_grid_cell(
            footprint,
            textile.thread_pitch_m,
            (xmax - xmin + 2.0 * margin) * (ymax - ymin + 2.0 * margin),
        );
        let x0 = xmin - margin;
        let y0 = ymin - margin;
        let nx = ((xmax - xmin + 2.0 * margin) / cell).ceil() as usize + 2;
        let ny = ((ymax - ymin + 2.0 * margin) / cell).ceil() as usize + 2;
        let mut heights = vec![0.0f32; nx * ny];
        heights.par_chunks_mut(nx).enumerate().for_each(|(j, row)| {
            for (i, h) in row.iter_mut().enumerate() {
                *h = textile.height_at(x0 + i as f64 * cell, y0 + j as f64 * cell) as f32;
            }
        });
        let max_height = heights.iter().fold(f32::MIN, |a, &b| a.max(b)) as f64;
        HeightGrid {
            x0,
            y0,
            cell,
            nx,
            ny,
            heights,
            max_height,
        }
    }

    /// Bilinear height at world `(x, y)`; `None` outside the grid.
    fn height(&self, x: f64, y: f64) -> Option<f64> {
        let gx = (x - self.x0) / self.cell;
        let gy = (y - self.y0) / self.cell;
        if gx < 0.0 || gy < 0.0 {
            return None;
        }
        let (i, j) = (gx as usize, gy as usize);
        if i + 1 >= self.nx || j + 1 >= self.ny {
            return None;
        }
        let (fx, fy) = (gx - i as f64, gy - j as f64);
        let h = |i: usize, j: usize| self.heights[j * self.nx + i] as f64;
        Some(
            (1.0 - fy) * ((1.0 - fx) * h(i, j) + fx * h(i + 1, j))
                + fy * ((1.0 - fx) * h(i, j + 1) + fx * h(i + 1, j + 1)),
        )
    }

    /// True when the relief blocks the straight line from the surface at `(x, y, h)` to the
    /// LED at `led`.
    fn shadowed(&self, x: f64, y: f64, h: f64, led: &Vector3<f64>) -> bool {
        let start_h = h.max(self.height(x, y).unwrap_or(h)) + 2e-6;
        let dir = (led - Vector3::new(x, y, start_h)).normalize();
        let horizontal = dir.x.hypot(dir.y);
        if horizontal < 1e-9 {
            return false;
        }
        let dt = 0.5 * self.cell / horizontal;
        let mut t = dt;
        loop {
            let (px, py, pz) = (x + dir.x * t, y + dir.y * t, start_h + dir.z * t);
            if pz > self.max_height {
                return false;
            }
            match self.height(px, py) {
                Some(surface) if surface > pz => return true,
                Some(_) => t += dt,
                None => return false,
            }
        }
    }
}
