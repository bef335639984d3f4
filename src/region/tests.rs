//! Region selection checked on rendered scenes: a crop solves as the crop of the full solve,
//! binning lowers the noise, the automatic mask finds the sample.

use super::*;
use crate::bench::{bench_noise, deviation_deg, render_scene, render_window, SceneKind};
use crate::eval;
use crate::progress::Silent;
use crate::rig::Rig;
use crate::solve::{solve, PixelStatus, SolveInput, SolveOptions, SolveResult};

fn run(rig: &Rig, frames: &Frames, mask: Option<&Mask>, scale: f64) -> SolveResult {
    let mut noise = bench_noise(rig);
    noise.channel_scale = noise.channel_scale.map(|c| c * scale);
    let input = SolveInput {
        frames,
        lights: LightSource::Rig(rig),
        noise,
        exposure: 1.0,
        mask,
    };
    let options = SolveOptions::exact(crate::solve::Estimator::LeastSquares);
    solve(&input, &options, &Silent).unwrap()
}

#[test]
fn a_cropped_solve_is_the_crop_of_the_full_solve() {
    let rig = Rig::default_rig();
    let (_, frames) = render_scene(&rig, SceneKind::Shadows, 0.05, &Silent).unwrap();
    let roi = Roi::parse("40,30,100,60").unwrap();
    let full = run(&rig, &frames, None, 1.0);
    let part = run(&rig, &crop(&frames, &roi).unwrap(), None, 1.0);
    let mut worst: f64 = 0.0;
    for y in 0..roi.height {
        for x in 0..roi.width {
            let i = (y + roi.y) * frames.width + x + roi.x;
            let j = y * roi.width + x;
            assert_eq!(part.status[j], full.status[i]);
            if full.status[i] == PixelStatus::Solved {
                worst = worst.max(eval::angle_deg(&part.normal_at(j), &full.normal_at(i)));
            }
        }
    }
    assert!(worst < 1e-4, "crop changed normals by {worst} deg");
    assert!(Roi::parse("1,2,3").is_err());
    assert!(crop(&frames, &Roi::parse("0,0,10000,5").unwrap()).is_err());
}

#[test]
fn binned_preview_has_a_quarter_of_the_pixels_and_less_noise() {
    let rig = Rig::default_rig();
    // Full resolution: a 2x2 block spans a fraction of a thread, as in a real preview.
    let (scene, frames) =
        render_window(&rig, SceneKind::Lambertian, (320, 240), 1.0, &Silent).unwrap();
    let full = run(&rig, &frames, None, 1.0);
    let binned_frames = bin2(&frames).unwrap();
    assert_eq!(binned_frames.width, frames.width / 2);
    let binned = run(&rig, &binned_frames, None, 0.25);
    let job = RegionJob {
        roi: None,
        bin: 2,
        background: Background::None,
    };
    let truth = (scene.truth.normal.clone(), scene.truth.albedo.clone());
    let (normal, albedo) = region_truth(truth, &job).unwrap();
    let e_full = eval::compare(&full, &scene.truth.normal, &scene.truth.albedo);
    let e_bin = eval::compare(&binned, &normal, &albedo);
    // Four samples per value: the noise part of the error halves; the textile's normals
    // vary inside a block, so the binned truth is only the Lambertian block average.
    assert!(
        e_bin.normal_error_deg.median < e_full.normal_error_deg.median,
        "binned {:?} vs full {:?}",
        e_bin.normal_error_deg,
        e_full.normal_error_deg
    );
}

/// The scene with everything outside a centred rectangle replaced by a flat black table
/// (albedo 0.02), rendered with the solver's own light model.
fn on_a_table(rig: &Rig, frames: &mut Frames) -> Mask {
    let (w, h) = (frames.width, frames.height);
    let ill = Illumination::new(
        &LightSource::Rig(rig),
        LightModel::Near,
        w,
        h,
        frames.window,
    )
    .unwrap();
    let mut sample = Mask::new(w, h, false);
    for y in 0..h {
        for x in 0..w {
            let inside = (w / 4..3 * w / 4).contains(&x) && (h / 5..4 * h / 5).contains(&y);
            sample.data[y * w + x] = inside;
            if inside {
                continue;
            }
            let p = ill.point(x, y).unwrap();
            for (k, f) in frames.lights.iter_mut().enumerate() {
                let s = ill.sample(k, &p);
                let scale = ill.rgb_scale(k);
                let v = |c: usize| (0.02 * scale[c] * s.falloff * s.direction.z) as f32;
                f.rgb.r.data[y * w + x] = v(0);
                f.rgb.g.data[y * w + x] = v(1);
                f.rgb.b.data[y * w + x] = v(2);
            }
        }
    }
    sample
}

#[test]
fn automatic_background_mask_finds_the_sample_and_skips_the_table() {
    let rig = Rig::default_rig();
    let (_, mut frames) = render_scene(&rig, SceneKind::Lambertian, 0.1, &Silent).unwrap();
    // Without a table, everything is sample.
    let (mask, info) = auto_mask(&frames, &LightSource::Rig(&rig)).unwrap();
    assert_eq!(mask.count(), frames.width * frames.height, "{info:?}");
    let truth = on_a_table(&rig, &mut frames);
    let (mask, info) = auto_mask(&frames, &LightSource::Rig(&rig)).unwrap();
    let wrong = mask
        .data
        .iter()
        .zip(&truth.data)
        .filter(|(a, b)| a != b)
        .count();
    // What the mask costs: sample pixels it calls table (dark thread gaps) are not solved.
    let lost = mask
        .data
        .iter()
        .zip(&truth.data)
        .filter(|(m, t)| **t && !**m)
        .count();
    assert!(info.threshold.is_some());
    assert!(
        wrong * 100 < truth.count(),
        "{wrong} misclassified, {lost} sample pixels lost, {info:?}"
    );
    let masked = run(&rig, &frames, Some(&mask), 1.0);
    let full = run(&rig, &frames, None, 1.0);
    assert_eq!(
        masked.count(PixelStatus::OutsideMask),
        mask.data.len() - mask.count()
    );
    assert_eq!(masked.count(PixelStatus::Solved), mask.count());
    // Inside the mask the solve is the same pixel for pixel.
    let (max, _) = deviation_deg(&masked, &full);
    assert_eq!(max, 0.0);
}

#[test]
fn a_region_past_the_frames_is_refused_even_when_its_numbers_overflow() {
    let huge = Roi {
        x: usize::MAX,
        y: 0,
        width: 10,
        height: 10,
    };
    let err = huge.check(320, 240).unwrap_err().to_string();
    assert!(err.contains("does not fit in the 320x240 frames"), "{err}");
    let inside = Roi {
        x: 310,
        y: 230,
        width: 10,
        height: 10,
    };
    assert!(inside.check(320, 240).is_ok());
    assert!(Roi { x: 311, ..inside }.check(320, 240).is_err());
}
