//! Solver tests against the synthetic rig's exact ground truth. Tolerances come from theory:
//! noise-free inputs must reproduce the truth to floating-point precision; noisy inputs must
//! match the predicted-error model.

use super::*;
use crate::eval::{self, normal_errors_deg};
use crate::plane::{LightFrame, RgbPlanes, SensorWindow};
use crate::progress::Silent;
use crate::raw::Levels;
use crate::rig::Rig;
use crate::synth::{expose, Noise, Scene, SceneOptions, SynthSpec, Textile};

/// The textile under the default rig, `width x height` pixels every `step` sensor pixels,
/// centred.
fn scene(rig: &Rig, width: usize, height: usize, step: f64) -> Scene<'_> {
    let window = SensorWindow::centred(
        rig.camera.width as usize,
        rig.camera.height as usize,
        width,
        height,
        step,
    );
    Scene::build(
        rig,
        Textile::default(),
        width,
        height,
        window,
        SceneOptions::default(),
        &Silent,
    )
    .unwrap()
}

fn solve_with(
    frames: &Frames,
    rig: &Rig,
    noise: NoiseModel,
    options: &SolveOptions,
) -> SolveResult {
    let input = SolveInput {
        frames,
        lights: LightSource::Rig(rig),
        noise,
        exposure: 1.0,
        mask: None,
    };
    solve(&input, options, &Silent).unwrap()
}

/// Frames as the sensor records them (noise, rounding, clipping) and decoded back.
fn noisy_frames(scene: &Scene, rig: &Rig, seed: u64) -> Frames {
    let levels = Levels::from_sensor(&rig.sensor);
    let lights = (0..rig.leds.len())
        .map(|k| {
            let linear = scene.render_light(k, 1.0);
            expose(&linear, &rig.sensor, Noise::Seeded(seed), k as u64 + 1).to_light_frame(&levels)
        })
        .collect();
    Frames {
        width: scene.width,
        height: scene.height,
        window: scene.window,
        lights,
    }
}

fn mean_error(result: &SolveResult, scene: &Scene) -> f64 {
    eval::compare(result, &scene.truth.normal, &scene.truth.albedo)
        .normal_error_deg
        .mean
}

#[test]
fn noise_free_near_light_solve_reproduces_the_truth_at_full_resolution() {
    let rig = Rig::default_rig();
    let scene = scene(&rig, 384, 256, 1.0);
    let frames = scene.render_ideal(1.0, &Silent);
    let result = solve_with(&frames, &rig, NoiseModel::NONE, &SolveOptions::default());
    let cmp = eval::compare(&result, &scene.truth.normal, &scene.truth.albedo);
    assert_eq!(
        cmp.pixels,
        384 * 256,
        "every pixel of a noise-free textile solves"
    );
    assert!(
        cmp.normal_error_deg.mean < 0.01,
        "{:?}",
        cmp.normal_error_deg
    );
    assert!(
        cmp.albedo_rel_error.mean < 1e-4,
        "{:?}",
        cmp.albedo_rel_error
    );
}

#[test]
fn noise_free_near_light_solve_is_exact_over_the_whole_field() {
    // Every 8th sensor pixel: the full 0.40 x 0.27 m field, where near-light effects are
    // largest, with attached shadows on the steep thread flanks under the low LEDs.
    let rig = Rig::default_rig();
    let scene = scene(&rig, 616, 408, 8.0);
    let frames = scene.render_ideal(1.0, &Silent);
    let result = solve_with(&frames, &rig, NoiseModel::NONE, &SolveOptions::default());
    let cmp = eval::compare(&result, &scene.truth.normal, &scene.truth.albedo);
    assert_eq!(cmp.pixels, 616 * 408);
    assert!(
        cmp.normal_error_deg.max < 0.01,
        "{:?}",
        cmp.normal_error_deg
    );
    assert!(
        cmp.albedo_rel_error.max < 1e-4,
        "{:?}",
        cmp.albedo_rel_error
    );
    // Attached shadows really occurred: some pixels had lights dropped as dark.
    assert!(result.lights_used.iter().any(|&n| n < 10));
}

#[test]
fn distant_lights_give_a_larger_low_frequency_error() {
    let rig = Rig::default_rig();
    let (w, h) = (616, 408);
    let scene = scene(&rig, w, h, 8.0);
    let frames = scene.render_ideal(1.0, &Silent);
    let near = solve_with(&frames, &rig, NoiseModel::NONE, &SolveOptions::default());
    let distant_options = SolveOptions {
        light_model: LightModel::Distant,
        ..SolveOptions::default()
    };
    let distant = solve_with(&frames, &rig, NoiseModel::NONE, &distant_options);
    let near_error = mean_error(&near, &scene);
    let distant_error = mean_error(&distant, &scene);
    assert!(
        distant_error > 100.0 * near_error && distant_error > 1.0,
        "near {near_error} deg, distant {distant_error} deg"
    );

    // Low frequency: the normal difference averaged over 32x32 blocks (21 mm on the table)
    // carries most of the difference's energy; an error uncorrelated from pixel to pixel
    // would leave 1/1024 of it in the block means. (Not all of it: how much a wrong light
    // direction tilts a normal depends on the normal, so the thread pattern shows through.)
    let block = 32;
    let (mut total, mut smooth) = (0.0, 0.0);
    for by in 0..h / block {
        for bx in 0..w / block {
            let mut mean = [0.0f64; 3];
            let mut energy = 0.0;
            for y in by * block..(by + 1) * block {
                for x in bx * block..(bx + 1) * block {
                    let i = y * w + x;
                    let d = distant.normal_at(i) - near.normal_at(i);
                    for c in 0..3 {
                        mean[c] += d[c];
                    }
                    energy += d.norm_squared();
                }
            }
            let n = (block * block) as f64;
            total += energy;
            smooth += mean.iter().map(|m| (m / n).powi(2)).sum::<f64>() * n;
        }
    }
    assert!(
        smooth / total > 0.5,
        "block means carry {:.3} of the error energy",
        smooth / total
    );

    // It grows toward the edges of the field (seed Figure 10).
    let errors = normal_errors_deg(&distant, &scene.truth.normal);
    let centre = errors[(h / 2) * w + w / 2].unwrap();
    let corner = errors[5 * w + 5].unwrap();
    assert!(
        corner > 3.0 * centre,
        "centre {centre} deg, corner {corner} deg"
    );
}

#[test]
fn noisy_solve_matches_the_predicted_error_model() {
    let rig = Rig::default_rig();
    let scene = scene(&rig, 512, 384, 4.0);
    let frames = noisy_frames(&scene, &rig, 11);
    let noise = NoiseModel::from_sensor(&rig.sensor);
    let result = solve_with(&frames, &rig, noise, &SolveOptions::default());
    let measured = mean_error(&result, &scene);
    let predicted = result.mean_predicted_error_deg();
    // The bound is 10 %; with 196k pixels the sampling error of the mean is ~0.2 %,
    // so a correct model lands well inside it.
    assert!(
        (measured / predicted - 1.0).abs() < 0.10,
        "measured {measured:.4} deg, predicted {predicted:.4} deg"
    );
    assert!(result.count(PixelStatus::Solved) > 512 * 384 * 99 / 100);
}

#[test]
fn svd_and_normal_equations_agree_on_well_conditioned_pixels() {
    let rig = Rig::default_rig();
    let scene = scene(&rig, 256, 192, 8.0);
    let frames = noisy_frames(&scene, &rig, 5);
    let noise = NoiseModel::from_sensor(&rig.sensor);
    let fast = solve_with(&frames, &rig, noise, &SolveOptions::default());
    let svd_options = SolveOptions {
        kernel: KernelChoice::Exact {
            method: Method::Svd,
            estimator: Estimator::default(),
        },
        ..SolveOptions::default()
    };
    let svd = solve_with(&frames, &rig, noise, &svd_options);
    let mut compared = 0;
    for i in 0..fast.status.len() {
        assert_eq!(fast.status[i], svd.status[i]);
        if fast.status[i] != PixelStatus::Solved || fast.condition.data[i] > 10.0 {
            continue;
        }
        let angle = eval::angle_deg(&fast.normal_at(i), &svd.normal_at(i));
        assert!(angle < 1e-4, "pixel {i}: {angle} deg apart");
        for c in 0..3 {
            let (a, b) = (fast.albedo[c].data[i], svd.albedo[c].data[i]);
            assert!((a - b).abs() <= 1e-5 * b.abs().max(1e-3));
        }
        assert!((fast.condition.data[i] / svd.condition.data[i] - 1.0).abs() < 1e-4);
        compared += 1;
    }
    assert!(
        compared > fast.status.len() * 9 / 10,
        "{compared} pixels compared"
    );
}

/// A 4x1 capture of a flat white patch under the default rig, every light at `value`.
fn flat_frames(rig: &Rig, value: f32) -> Frames {
    let window = SensorWindow::centred(
        rig.camera.width as usize,
        rig.camera.height as usize,
        4,
        1,
        1.0,
    );
    let lights = rig
        .leds
        .iter()
        .map(|_| {
            let mut rgb = RgbPlanes::new(4, 1);
            for p in [&mut rgb.r, &mut rgb.g, &mut rgb.b] {
                p.data.fill(value);
            }
            LightFrame {
                rgb,
                saturated: Some(crate::plane::Mask::new(4, 1, false)),
                cfa: None,
                dn: None,
                cfa_dn: None,
            }
        })
        .collect();
    Frames {
        width: 4,
        height: 1,
        window,
        lights,
    }
}

fn assert_all_finite(result: &SolveResult) {
    let planes = result.normal.iter().chain(&result.albedo).chain([
        &result.residual,
        &result.predicted_error_deg,
        &result.condition,
    ]);
    for plane in planes {
        assert!(plane.data.iter().all(|v| v.is_finite()));
    }
}

#[test]
fn degenerate_pixels_are_masked_with_their_reason_and_never_nan() {
    let rig = Rig::default_rig();
    let mut frames = flat_frames(&rig, 0.3);
    for (k, frame) in frames.lights.iter_mut().enumerate() {
        // Pixel 0: black in every light.
        frame.rgb.r.data[0] = 0.0;
        frame.rgb.g.data[0] = 0.0;
        frame.rgb.b.data[0] = 0.0;
        // Pixel 1: saturated in every light.
        frame.saturated.as_mut().unwrap().data[1] = true;
        // Pixel 2: NaN or infinite everywhere.
        frame.rgb.g.data[2] = if k % 2 == 0 { f32::NAN } else { f32::INFINITY };
        // Pixel 3: NaN in one light only: still solvable from the other nine.
        if k == 4 {
            frame.rgb.r.data[3] = f32::NAN;
        }
    }
    let noise = NoiseModel::from_sensor(&rig.sensor);
    for (method, estimator) in [Method::NormalEquations, Method::Svd]
        .into_iter()
        .flat_map(|m| Estimator::ALL.map(|e| (m, e)))
    {
        let options = SolveOptions {
            kernel: KernelChoice::Exact { method, estimator },
            ..SolveOptions::default()
        };
        let result = solve_with(&frames, &rig, noise, &options);
        assert_eq!(
            result.status,
            vec![
                PixelStatus::Dark,
                PixelStatus::Saturated,
                PixelStatus::NonFinite,
                PixelStatus::Solved
            ]
        );
        // Equal readings under every light are not Lambertian: least squares uses all nine
        // finite lights, the robust fits reject some (never below three).
        if estimator == Estimator::LeastSquares {
            assert_eq!(result.lights_used[3], 9);
        } else {
            assert!((3..=9).contains(&result.lights_used[3]));
        }
        assert_all_finite(&result);
        for i in 0..3 {
            assert_eq!(result.normal_at(i), nalgebra::Vector3::new(0.0, 0.0, 1.0));
        }
    }
}

#[test]
fn coplanar_lights_are_flagged_degenerate() {
    // Three LEDs on one vertical plane through the sample: their directions are coplanar, so
    // the normal's component across that plane is unobservable.
    let mut rig = Rig::default_rig();
    rig.leds.truncate(3);
    rig.leds[0].position_m = [0.3, 0.0, 0.3];
    rig.leds[1].position_m = [-0.3, 0.0, 0.3];
    rig.leds[2].position_m = [0.0, 0.0, 0.5];
    let mut frames = flat_frames(&rig, 0.3);
    frames.window = SensorWindow::centred(4928, 3264, 4, 1, 1.0);
    // The centre pixels lie almost exactly on y = 0, the plane of the three LEDs.
    let result = solve_with(&frames, &rig, NoiseModel::NONE, &SolveOptions::default());
    assert!(
        result.status.iter().all(|&s| s == PixelStatus::Degenerate),
        "{:?}",
        result.status
    );
    assert_all_finite(&result);
}

#[test]
fn exactly_three_lights_solve_exactly() {
    let mut rig = Rig::default_rig();
    rig.leds = vec![
        rig.leds[0].clone(),
        rig.leds[2].clone(),
        rig.leds[7].clone(),
    ];
    let scene = scene(&rig, 64, 64, 16.0);
    let frames = scene.render_ideal(1.0, &Silent);
    let result = solve_with(&frames, &rig, NoiseModel::NONE, &SolveOptions::default());
    let errors: Vec<f64> = normal_errors_deg(&result, &scene.truth.normal)
        .into_iter()
        .flatten()
        .collect();
    // Pixels where a light is in attached shadow keep only two lights and are masked; the
    // rest are exact.
    assert!(errors.len() > 64 * 64 / 2, "{} solved", errors.len());
    assert!(errors.iter().all(|&e| e < 0.01));
    for i in 0..result.status.len() {
        if result.status[i] != PixelStatus::Solved {
            assert_eq!(result.status[i], PixelStatus::Dark);
            assert!(result.lights_used[i] < 3);
        }
    }
}

#[test]
fn pixels_outside_the_mask_are_not_solved() {
    let rig = Rig::default_rig();
    let frames = flat_frames(&rig, 0.3);
    let mut mask = crate::plane::Mask::new(4, 1, true);
    mask.data[2] = false;
    let input = SolveInput {
        frames: &frames,
        lights: LightSource::Rig(&rig),
        noise: NoiseModel::NONE,
        exposure: 1.0,
        mask: Some(&mask),
    };
    let result = solve(&input, &SolveOptions::default(), &Silent).unwrap();
    assert_eq!(result.status[2], PixelStatus::OutsideMask);
    assert_eq!(result.count(PixelStatus::Solved), 3);
}

#[test]
fn mismatched_inputs_are_refused_with_a_reason() {
    let rig = Rig::default_rig();
    let mut frames = flat_frames(&rig, 0.3);
    frames.lights.pop();
    let input = SolveInput {
        frames: &frames,
        lights: LightSource::Rig(&rig),
        noise: NoiseModel::NONE,
        exposure: 1.0,
        mask: None,
    };
    let err = solve(&input, &SolveOptions::default(), &Silent)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("9 light frames") && err.contains("10 lights"),
        "{err}"
    );
}

#[test]
fn exposure_scales_albedo_only() {
    let rig = Rig::default_rig();
    let spec = SynthSpec {
        width: 32,
        height: 32,
        step: 32.0,
        ..SynthSpec::demo()
    };
    let scene = Scene::build(
        &rig,
        spec.textile.clone(),
        32,
        32,
        spec.window(&rig),
        SceneOptions::default(),
        &Silent,
    )
    .unwrap();
    let frames = scene.render_ideal(0.5, &Silent);
    let input = SolveInput {
        frames: &frames,
        lights: LightSource::Rig(&rig),
        noise: NoiseModel::NONE,
        exposure: 0.5,
        mask: None,
    };
    let result = solve(&input, &SolveOptions::default(), &Silent).unwrap();
    let cmp = eval::compare(&result, &scene.truth.normal, &scene.truth.albedo);
    assert!(cmp.albedo_rel_error.max < 1e-4 && cmp.normal_error_deg.max < 0.01);
}

/// A full-resolution RAW pixel's light is dark when its own CFA sample is within
/// `dark_threshold_sigma` (3) deviations of that sample's noise floor, on every kernel. Its
/// luminance is the sample times the pixel's colour factor: at a green site of a red
/// material (R : G : B = 0.42 : 0.05 : 0.05) about 2.6, and tested as three independent
/// channels' luminance (floor deviation 0.75 of one channel's) the bar sat at 0.88 deviations
/// of the sample, so a light in attached shadow reading 1.5 deviations of noise was used.
#[test]
fn a_raw_pixels_dark_test_is_on_its_own_sample() {
    use crate::plane::{CfaColour, Plane};
    let rig = Rig::default_rig();
    let (w, h) = (32, 4);
    let pattern = [[0u8, 1], [1, 2]];
    let red = [0.42f32, 0.05, 0.05];
    let mut ratios = RgbPlanes::new(w, h);
    ratios.par_rows_mut(|y, rows| {
        for x in 0..w {
            let own = pattern[y % 2][x % 2] as usize;
            for c in 0..3 {
                rows[c][x] = red[c] / red[own];
            }
        }
    });
    let ratios = std::sync::Arc::new(ratios);
    let base = crate::bench::bench_noise(&rig);
    let sigma = base.floor.sqrt() as f32;
    let green_sites: Vec<usize> = (0..w * h)
        .filter(|&i| pattern[(i / w) % 2][(i % w) % 2] == 1)
        .collect();
    // Light 0 reads `dark` (noise in attached shadow); the other nine are well lit.
    let frames_with = |dark: f32| Frames {
        width: w,
        height: h,
        window: SensorWindow::centred(
            rig.camera.width as usize,
            rig.camera.height as usize,
            w,
            h,
            1.0,
        ),
        lights: (0..rig.leds.len())
            .map(|k| {
                let sample = Plane::from_vec(
                    w,
                    h,
                    (0..w * h)
                        .map(|i| {
                            let own = pattern[(i / w) % 2][(i % w) % 2] as usize;
                            if k == 0 {
                                dark
                            } else {
                                red[own] * (0.5 + 0.04 * k as f32)
                            }
                        })
                        .collect(),
                )
                .unwrap();
                LightFrame::from_cfa(
                    sample,
                    None,
                    CfaColour {
                        pattern,
                        ratios: std::sync::Arc::clone(&ratios),
                        colour: [1.0; 3],
                    },
                )
            })
            .collect(),
    };
    let shared = NoiseModel {
        shared_cfa_sample: Some(pattern),
        ..base
    };
    let kernels = [
        SolveOptions::exact(Estimator::LeastSquares),
        SolveOptions::exact(Estimator::LeastSquares).with_default_kernel(),
    ];
    for options in &kernels {
        for (dark, used) in [(1.5 * sigma, 9), (4.0 * sigma, 10)] {
            let result = solve_with(&frames_with(dark), &rig, shared, options);
            for &i in &green_sites {
                assert_eq!(
                    result.lights_used[i],
                    used,
                    "{:?}: light 0 at {} deviations, pixel {i}",
                    options.kernel,
                    dark / sigma
                );
            }
        }
        // The same values as independent channels (no shared sample): the luminance,
        // 2.6 x 1.5 = 3.9 deviations of the sample against a bar of 3 x 0.75, is bright.
        let result = solve_with(&frames_with(1.5 * sigma), &rig, base, options);
        for &i in &green_sites {
            assert_eq!(result.lights_used[i], 10, "{:?}: pixel {i}", options.kernel);
        }
    }
}

#[test]
fn class_counts_are_the_counts_of_each_status_and_fit() {
    // Over several blocks of the parallel count, every status and fit mixed, some fits on
    // pixels that are not solved (which the fit counts leave out).
    let (w, h) = (1000, 200);
    let mut result = SolveResult::new(w, h);
    for i in 0..w * h {
        result.status[i] = PixelStatus::ALL[(i * 7 / 3) % 6];
        result.fit[i] = PixelFit::ALL[(i / 5) % 3];
    }
    let (statuses, fits) = result.class_counts();
    for (k, &s) in PixelStatus::ALL.iter().enumerate() {
        assert_eq!(statuses[k], result.count(s), "{s:?}");
        assert!(statuses[k] > 0);
    }
    for (k, &f) in PixelFit::ALL.iter().enumerate() {
        assert_eq!(fits[k], result.count_fit(f), "{f:?}");
        assert!(fits[k] > 0);
    }
    assert!(
        fits.iter().sum::<usize>() < w * h,
        "unsolved pixels' fits are not counted"
    );
}
