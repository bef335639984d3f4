//! Synthetic capture sets stored as DNG files (the path real RAW files take) against the same
//! scenes stored as dn16 RGB frames and against the predicted-error model, at full and at half
//! resolution. Tolerances come from the noise model; the sets are small (256 x 192 sensor
//! pixels at full resolution, 82 um each) to keep the run short.

use std::path::Path;

use psscan::capture::CaptureSet;
use psscan::eval::{self, Stats};
use psscan::plane::Plane;
use psscan::progress::Silent;
use psscan::raw::{self, DevelopOptions, Mosaic, Resolution};
use psscan::rig::Rig;
use psscan::sets::{self, SolveJob};
use psscan::solve::{self, PixelStatus, SolveInput, SolveResult};
use psscan::synth::{self, expose_mosaic, FrameEncoding, Noise, Scene, SynthSpec};

const W: usize = 256;
const H: usize = 192;

fn spec(encoding: FrameEncoding, noise: Option<u64>) -> SynthSpec {
    SynthSpec {
        width: W,
        height: H,
        step: 1.0,
        noise_seed: noise,
        encoding,
        ..SynthSpec::demo()
    }
}

/// The default rig with ten times the electrons per DN: a high signal-to-noise capture, where
/// the predicted-error model (first order in the noise) is accurate for every CFA site. At the
/// default gain the weakest sites (R under the navy and green threads) reach a few degrees of
/// noise and the first-order model underestimates them by up to ~15 %.
fn quiet_rig() -> Rig {
    let mut rig = Rig::default_rig();
    rig.sensor.gain_e_per_dn *= 10.0;
    rig
}

struct Solved {
    result: SolveResult,
    normal_truth: [Plane; 3],
    albedo_truth: [Plane; 3],
    info: raw::DecodeInfo,
}

fn write_and_solve(rig: &Rig, spec: &SynthSpec, resolution: Resolution, dir: &Path) -> Solved {
    synth::write_synthetic_set(rig, spec, dir, false, &Silent).unwrap();
    let set = CaptureSet::open(dir, None).unwrap();
    let options = DevelopOptions {
        resolution,
        subtract_dark: true,
    };
    let loaded = set.load_frames_with(&options, &Silent).unwrap();
    let input = SolveInput {
        frames: &loaded.frames,
        lights: solve::LightSource::Rig(&set.rig),
        noise: sets::decoded_noise_model(&set.rig, &loaded.info),
        exposure: 1.0,
        mask: None,
    };
    let result = solve::solve(&input, &SolveJob::default().options, &Silent).unwrap();
    let (normal_truth, albedo_truth) = sets::truth_for(&set, &loaded.info).unwrap().unwrap();
    Solved {
        result,
        normal_truth,
        albedo_truth,
        info: loaded.info,
    }
}

fn errors(s: &Solved) -> Stats {
    eval::compare(&s.result, &s.normal_truth, &s.albedo_truth).normal_error_deg
}

/// Mean measured and predicted error over the solved pixels `keep` accepts.
fn measured_and_predicted(s: &Solved, keep: impl Fn(usize) -> bool) -> (f64, f64, usize) {
    let errors = eval::normal_errors_deg(&s.result, &s.normal_truth);
    let (mut measured, mut predicted, mut n) = (0.0, 0.0, 0);
    for (i, e) in errors.iter().enumerate() {
        if let (Some(e), true) = (e, keep(i)) {
            measured += e;
            predicted += s.result.predicted_error_deg.data[i] as f64;
            n += 1;
        }
    }
    (measured / n as f64, predicted / n as f64, n)
}

#[test]
fn render_to_dng_to_decode_returns_the_rendered_values_within_quantisation() {
    let rig = Rig::default_rig();
    let spec = spec(FrameEncoding::Dng, None);
    let window = spec.window(&rig);
    let scene = Scene::build(
        &rig,
        spec.textile.clone(),
        W,
        H,
        window,
        spec.scene.clone(),
        &Silent,
    )
    .unwrap();
    let pattern = Mosaic::parse_pattern(synth::set::SYNTH_CFA).unwrap();
    let s = &rig.sensor;
    let full_scale = (s.white_level - s.black_level) as f32;
    for k in [0, 7] {
        let linear = scene.render_light(k, 1.0);
        let mosaic = Mosaic {
            width: W,
            height: H,
            pattern,
            black: [[s.black_level as f32; 2]; 2],
            white: s.white_level as f32,
            samples: expose_mosaic(&linear, pattern, s, Noise::Off, 0),
        };
        let meta = raw::RawMeta {
            make: "psscan".into(),
            model: "test".into(),
            width: W,
            height: H,
            iso: Some(100),
            shutter_s: Some(0.1),
            aperture: Some(8.0),
        };
        let bytes = raw::encode_dng(
            &mosaic,
            &meta,
            s.bits,
            s.channel_gain,
            raw::DngStorage::Lossless,
        )
        .unwrap();
        let decoded = raw::decode_raw(bytes, Path::new("L.dng")).unwrap();
        assert_eq!(decoded.meta, meta);
        let back = decoded.mosaic.linearize().unwrap();
        for y in 0..H {
            for x in 0..W {
                let i = y * W + x;
                let truth = linear.channels()[back.channel(x, y)].data[i];
                // Rounding to whole DN: half a DN, plus float rounding.
                assert!(
                    (back.values[i] - truth).abs() <= 0.5 / full_scale + 1e-6,
                    "light {k} ({x},{y}): {} vs {truth}",
                    back.values[i]
                );
                assert!(!back.saturated[i]);
            }
        }
    }
}

#[test]
fn a_dng_set_at_full_resolution_solves_to_the_noise_limit_of_its_sensor() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let rig = Rig::default_rig();

    // Noise-free: only 14-bit quantisation remains. The demosaic adds no model error: every
    // pixel's shading is its own (a plain bilinear demosaic scores about 6.6 deg here).
    let clean_dng = write_and_solve(
        &rig,
        &spec(FrameEncoding::Dng, None),
        Resolution::Full,
        &root.join("a"),
    );
    let clean_dn16 = write_and_solve(
        &rig,
        &spec(FrameEncoding::Dn16, None),
        Resolution::Full,
        &root.join("b"),
    );
    assert_eq!(clean_dng.result.count(PixelStatus::Solved), W * H);
    let (dng, dn16) = (errors(&clean_dng).mean, errors(&clean_dn16).mean);
    // Quantisation of one sample per pixel instead of three, at low signal on R and B sites:
    // a few hundredths of a degree (measured 0.019 and 0.008 at 512 x 384).
    eprintln!("full resolution, noise-free: dng {dng:.4} deg, dn16 {dn16:.4} deg");
    assert!(
        dng < 0.05 && dn16 < 0.05,
        "noise-free: dng {dng} deg, dn16 {dn16} deg"
    );
    assert_eq!(
        clean_dng.info.noise_shared_cfa_sample.as_deref(),
        Some("RGGB")
    );

    // With sensor noise: the DNG set's error is what the noise model predicts for a Bayer
    // sensor (each pixel one sample, all its channels sharing that sample's noise), and the
    // dn16 set's what it predicts for three samples per pixel. At 49k pixels the sampling
    // error of a mean is ~0.5 %.
    let quiet = quiet_rig();
    let noisy_dng = write_and_solve(
        &quiet,
        &spec(FrameEncoding::Dng, Some(3)),
        Resolution::Full,
        &root.join("c"),
    );
    let noisy_dn16 = write_and_solve(
        &quiet,
        &spec(FrameEncoding::Dn16, Some(3)),
        Resolution::Full,
        &root.join("d"),
    );
    let (m_dng, p_dng, _) = measured_and_predicted(&noisy_dng, |_| true);
    let (m_dn16, p_dn16, _) = measured_and_predicted(&noisy_dn16, |_| true);
    eprintln!(
        "full resolution, noisy (10x electrons): dng {m_dng:.4} deg (predicted {p_dng:.4}), dn16 {m_dn16:.4} deg (predicted {p_dn16:.4})"
    );
    assert!(
        (m_dng / p_dng - 1.0).abs() < 0.05,
        "dng measured {m_dng}, predicted {p_dng}"
    );
    assert!(
        (m_dn16 / p_dn16 - 1.0).abs() < 0.05,
        "dn16 measured {m_dn16}, predicted {p_dn16}"
    );
    // The DNG set is worse than dn16 exactly by the sensor's noise (a third of the samples).
    let excess = (m_dng / m_dn16) / (p_dng / p_dn16);
    assert!(
        (excess - 1.0).abs() < 0.05,
        "dng/dn16 measured {} vs predicted {}",
        m_dng / m_dn16,
        p_dng / p_dn16
    );
}

/// True for binned cells whose four CFA sites all face every LED (by more than a few degrees):
/// where a binned pixel is exactly a Lambertian pixel of the binned normal.
fn fully_lit_cells(rig: &Rig, spec: &SynthSpec, normal: &[Plane; 3]) -> Vec<bool> {
    let window = spec.window(rig);
    let mapper = rig.camera.plane_mapper(rig.sample.z_m);
    let (w, h) = Resolution::Half.size(W, H);
    let mut lit = vec![true; w * h];
    for v in 0..h {
        for u in 0..w {
            for j in 0..2 {
                for i in 0..2 {
                    let (x, y) = (2 * u + i, 2 * v + j);
                    let (sx, sy) = window.to_sensor(x as f64, y as f64);
                    let point = mapper.map(sx, sy).unwrap();
                    let n = nalgebra::Vector3::from_fn(|c, _| normal[c].data[y * W + x] as f64);
                    for led in &rig.leds {
                        if n.dot(&led.sample_at(&point).direction) < 0.05 {
                            lit[v * w + u] = false;
                        }
                    }
                }
            }
        }
    }
    lit
}

#[test]
fn a_dng_set_at_half_resolution_measures_the_binned_surface() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let rig = quiet_rig();
    let clean_spec = spec(FrameEncoding::Dng, None);
    let clean = write_and_solve(&rig, &clean_spec, Resolution::Half, &root.join("a"));
    let set = CaptureSet::open(&root.join("a"), None).unwrap();
    let (full_normal, _) = sets::read_truth(&set).unwrap().unwrap();
    let lit = fully_lit_cells(&rig, &clean_spec, &full_normal);
    let lit_count = lit.iter().filter(|&&l| l).count();
    assert!(lit_count > lit.len() / 5, "{lit_count} fully lit cells");

    // Where all four sites face every light the binned pixel is exactly Lambertian with the
    // binned normal: the error is quantisation.
    let (clean_lit, _, _) = measured_and_predicted(&clean, |i| lit[i]);
    let all = errors(&clean).mean;
    eprintln!("half resolution, noise-free: fully lit cells ({lit_count}) {clean_lit:.4} deg, all cells {all:.4} deg");
    assert!(
        clean_lit < 0.05,
        "noise-free, fully lit cells: {clean_lit} deg"
    );
    // Cells straddling an attached-shadow boundary of some light are not Lambertian once
    // binned (part of the cell is dark): that is binning's own error on a steep weave.
    let (clean_edge, _, _) = measured_and_predicted(&clean, |i| !lit[i]);
    assert!(
        clean_edge > 10.0 * clean_lit,
        "shadow-boundary cells: {clean_edge} deg"
    );

    // With noise, in the fully lit cells the error is the noise model's (R, B single samples,
    // G the mean of two, independent). 12k cells, a fifth or more of them lit: ~1 % sampling.
    let noisy = write_and_solve(
        &rig,
        &spec(FrameEncoding::Dng, Some(4)),
        Resolution::Half,
        &root.join("b"),
    );
    let (m, p, n) = measured_and_predicted(&noisy, |i| lit[i]);
    eprintln!(
        "half resolution, noisy (10x electrons): fully lit cells {m:.4} deg (predicted {p:.4}), all cells {:.4} deg",
        errors(&noisy).mean
    );
    assert!(
        (m / p - 1.0).abs() < 0.05,
        "fully lit cells ({n}): measured {m}, predicted {p}"
    );
    assert_eq!(noisy.info.noise_channel_scale, [1.0, 0.5, 1.0]);
    assert_eq!(noisy.result.width, W / 2);
}
