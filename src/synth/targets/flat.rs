//! Flat calibration targets lying on the table, lit by each LED: the white sheet (with its
//! fibre texture) and the gray chart's patches, rendered as linear frames and as the raw
//! mosaics the sensor records.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;

use super::binned_size;
use crate::plane::{Frames, LightFrame, RgbPlanes, SensorWindow};
use crate::rig::Rig;
use crate::synth::sensor::{expose, Noise};

/// Renders the linear RGB image (1.0 = white level) of a flat, Lambertian target lying on the
/// table at the sample plane, lit by LED `k` of `rig`, through `window`. `reflectance(x, y)`
/// gives the target's RGB reflectance at world `(x, y)`.
pub fn render_flat_target(
    rig: &Rig,
    window: SensorWindow,
    width: usize,
    height: usize,
    k: usize,
    exposure: f64,
    reflectance: &(dyn Fn(f64, f64) -> [f64; 3] + Sync),
) -> RgbPlanes {
    let mapper = rig.camera.plane_mapper(rig.sample.z_m);
    let led = &rig.leds[k];
    let scale = rig.led_rgb_power(k).map(|c| c / led.power * exposure);
    let mut out = RgbPlanes::new(width, height);
    out.par_rows_mut(|y, rows| {
        for x in 0..width {
            let (u, v) = window.to_sensor(x as f64, y as f64);
            let Some(p) = mapper.map(u, v) else { continue };
            let light = led.sample_at(&p);
            let shade = light.falloff * light.direction.z.max(0.0);
            let rho = reflectance(p.x, p.y);
            for c in 0..3 {
                rows[c][x] = (shade * scale[c] * rho[c]) as f32;
            }
        }
    });
    out
}

/// A white sheet with paper texture: reflectance `mean` modulated by a fine, seeded fibre
/// pattern of relative amplitude `texture` (zero mean over a few millimetres).
pub fn white_sheet(mean: f64, texture: f64, seed: u64) -> impl Fn(f64, f64) -> [f64; 3] + Sync {
    let phase: [f64; 4] = {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        std::array::from_fn(|_| rng.gen_range(0.0..std::f64::consts::TAU))
    };
    move |x, y| {
        // Fibres about 0.5-1 mm across: far finer than any light's falloff.
        let t = (x * 9000.0 + phase[0]).sin() * (y * 7000.0 + phase[1]).sin()
            + 0.5 * ((x + y) * 13000.0 + phase[2]).sin()
            + 0.5 * ((x - 0.7 * y) * 11000.0 + phase[3]).sin();
        let r = mean * (1.0 + texture * t / 2.0);
        [r, r, r]
    }
}

/// The white sheet (reflectance `reflectance`, fibre texture of relative amplitude
/// `texture`) on the table under each LED of `rig`, photographed `exposures` times through the
/// sensor (noise seeded) and averaged, as linear frames of the whole sensor binned by `step`.
pub fn white_sheet_frames(
    rig: &Rig,
    step: f64,
    reflectance: f64,
    texture: f64,
    exposures: usize,
    seed: u64,
) -> Frames {
    let (w, h) = binned_size(rig, step);
    let window = SensorWindow::centred(
        rig.camera.width as usize,
        rig.camera.height as usize,
        w,
        h,
        step,
    );
    let sheet = white_sheet(reflectance, texture, seed);
    flat_target_frames(rig, window, (w, h), &sheet, exposures, seed)
}

/// Any flat target on the table under each LED, exposed `exposures` times and averaged.
pub fn flat_target_frames(
    rig: &Rig,
    window: SensorWindow,
    (w, h): (usize, usize),
    reflectance: &(dyn Fn(f64, f64) -> [f64; 3] + Sync),
    exposures: usize,
    seed: u64,
) -> Frames {
    let levels = crate::raw::Levels::from_sensor(&rig.sensor);
    let lights = (0..rig.leds.len())
        .map(|k| {
            let linear = render_flat_target(rig, window, w, h, k, 1.0, reflectance);
            let mut sum: Option<LightFrame> = None;
            for e in 0..exposures.max(1) {
                let stream = (k as u64 + 1) * 1000 + e as u64;
                let frame = expose(&linear, &rig.sensor, Noise::Seeded(seed ^ 0x5eed), stream)
                    .to_light_frame(&levels);
                sum = Some(match sum {
                    None => frame,
                    Some(mut acc) => {
                        for (a, b) in [
                            (&mut acc.rgb.r, &frame.rgb.r),
                            (&mut acc.rgb.g, &frame.rgb.g),
                            (&mut acc.rgb.b, &frame.rgb.b),
                        ] {
                            for (x, y) in a.data.iter_mut().zip(&b.data) {
                                *x += y;
                            }
                        }
                        if let (Some(m), Some(o)) =
                            (acc.saturated.as_mut(), frame.saturated.as_ref())
                        {
                            for (x, y) in m.data.iter_mut().zip(&o.data) {
                                *x |= *y;
                            }
                        }
                        acc
                    }
                });
            }
            let mut frame = sum.expect("at least one exposure");
            let n = exposures.max(1) as f32;
            for plane in [&mut frame.rgb.r, &mut frame.rgb.g, &mut frame.rgb.b] {
                for v in plane.data.iter_mut() {
                    *v /= n;
                }
            }
            frame
        })
        .collect();
    Frames {
        width: w,
        height: h,
        window,
        lights,
    }
}

/// The reflectance of `chart` lying on the table with its patches filling the world
/// rectangle `[x0, x1, y0, y1]` (metres; row 0 at the top of the image, world +y), on a dark
/// mount (0.2) around it.
pub fn gray_chart(
    chart: &crate::rig::ChartDescription,
    world: [f64; 4],
) -> impl Fn(f64, f64) -> [f64; 3] + Sync + '_ {
    let [x0, x1, y0, y1] = world;
    let (rows, cols) = (chart.rows, chart.cols);
    move |x: f64, y: f64| {
        if x < x0 || x >= x1 || y < y0 || y >= y1 {
            return [0.2; 3];
        }
        let c = (((x - x0) / (x1 - x0)) * cols as f64) as usize;
        let r = (((y1 - y) / (y1 - y0)) * rows as f64) as usize;
        [chart.reflectance[r.min(rows - 1) * cols + c.min(cols - 1)]; 3]
    }
}

/// The gray chart (`chart`'s patches filling the world rectangle `x0..x1`, `y0..y1` on the
/// table, metres) photographed under each LED as raw RGGB mosaics of a `width x height` window
/// centred on the sensor, every `step` pixels, at `exposure`; and the chart's rectangle in the
/// image (the projection of its world corners: what a user marks).
pub fn gray_chart_mosaics(
    rig: &Rig,
    chart: &crate::rig::ChartDescription,
    world: [f64; 4],
    (width, height, step): (usize, usize, f64),
    exposure: f64,
    seed: u64,
) -> (Vec<crate::raw::Mosaic>, crate::rig::ChartRect) {
    let window = SensorWindow::centred(
        rig.camera.width as usize,
        rig.camera.height as usize,
        width,
        height,
        step,
    );
    let [x0, x1, y0, y1] = world;
    let reflectance = gray_chart(chart, world);
    let pattern = [[0u8, 1], [1, 2]];
    let black = rig.sensor.black_level as f32;
    let mosaics = (0..rig.leds.len())
        .map(|k| {
            let linear = render_flat_target(rig, window, width, height, k, exposure, &reflectance);
            crate::raw::Mosaic {
                width,
                height,
                pattern,
                black: [[black; 2]; 2],
                white: rig.sensor.white_level as f32,
                samples: crate::synth::sensor::expose_mosaic(
                    &linear,
                    pattern,
                    &rig.sensor,
                    Noise::Seeded(seed),
                    k as u64 + 1,
                ),
            }
        })
        .collect();
    let to_image = |x: f64, y: f64| {
        let (u, v) = rig
            .camera
            .project(&Vector3::new(x, y, rig.sample.z_m))
            .expect("in front of the camera");
        ((u - window.x0) / window.step, (v - window.y0) / window.step)
    };
    let (ax, ay) = to_image(x0, y1);
    let (bx, by) = to_image(x1, y0);
    (
        mosaics,
        crate::rig::ChartRect {
            x0: ax,
            y0: ay,
            x1: bx,
            y1: by,
        },
    )
}
