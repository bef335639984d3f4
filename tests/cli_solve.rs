//! End-to-end tests of the `psscan solve` options that change what is solved and how
//! (`--estimator`, `--precision`, `--tile-tolerance`, `--sheen-fit`, `--normal-only`, `--roi`,
//! `--bin`, `--background`), and of `psscan bench --json` at a tiny size. Every check is on the
//! solve's real output against the synthetic set's ground truth or against another solve of
//! the same frames, with bounds from the noise model or from geometry, not from a past run.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

mod common;

use common::{json, psscan, s, stderr};
use serde_json::Value;

/// Width and height of the synthetic sets: every 16th sensor pixel over the whole field.
const W: usize = 256;
const H: usize = 160;

/// The sets, rendered once for all tests: `lambertian` and `shadows+sheen` (the demo's
/// `--shadows --sheen` scene), with sensor noise.
struct Sets {
    _dir: tempfile::TempDir,
    lambertian: PathBuf,
    hard: PathBuf,
}

fn sets() -> &'static Sets {
    static SETS: OnceLock<Sets> = OnceLock::new();
    SETS.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let lambertian = dir.path().join("lambertian");
        let hard = dir.path().join("hard");
        let (w, h) = (W.to_string(), H.to_string());
        let base = ["--width", &w, "--height", &h, "--step", "16", "--json"];
        json(&psscan(
            &[&["synth", "--out", s(&lambertian)], &base[..]].concat(),
        ));
        json(&psscan(
            &[
                &["synth", "--out", s(&hard), "--shadows", "--sheen"],
                &base[..],
            ]
            .concat(),
        ));
        Sets {
            _dir: dir,
            lambertian,
            hard,
        }
    })
}

/// Solves `set` with `flags` into a fresh folder; returns the report and the folder.
fn solve(set: &Path, flags: &[&str]) -> (Value, tempfile::TempDir) {
    let out = tempfile::tempdir().unwrap();
    let maps = out.path().join("maps");
    let report = json(&psscan(
        &[&["solve", s(set), "--out", s(&maps), "--json"], flags].concat(),
    ));
    (report, out)
}

/// Runs `psscan solve SET --out OUT FLAGS...`, which must be refused (exit 1) with `needle` in
/// its error.
fn assert_refused(set: &Path, out: &Path, flags: &[&str], needle: &str) {
    let output = psscan(&[&["solve", s(set), "--out", s(out)], flags].concat());
    assert_eq!(output.status.code(), Some(1));
    assert!(stderr(&output).contains(needle), "{}", stderr(&output));
}

fn mean_error(report: &Value) -> f64 {
    report["truth"]["normal_error_deg"]["mean"]
        .as_f64()
        .unwrap()
}

fn predicted(report: &Value) -> f64 {
    report["predicted_normal_error_deg"]["mean"]
        .as_f64()
        .unwrap()
}

fn count(report: &Value, group: &str, key: &str) -> u64 {
    report[group][key].as_u64().unwrap_or(0)
}

fn normals(dir: &Path) -> [psscan::plane::Plane; 3] {
    let planes =
        psscan::io::read_exr(&dir.join("maps/normal.exr"), &["R", "G", "B"]).expect("normal.exr");
    [planes[0].clone(), planes[1].clone(), planes[2].clone()]
}

/// Largest angle (degrees) between two normal maps of the same size.
fn max_angle(a: &[psscan::plane::Plane; 3], b: &[psscan::plane::Plane; 3]) -> f64 {
    let v = |n: &[psscan::plane::Plane; 3], i: usize| {
        nalgebra::Vector3::new(n[0].data[i], n[1].data[i], n[2].data[i]).cast::<f64>()
    };
    (0..a[0].data.len())
        .map(|i| psscan::eval::angle_deg(&v(a, i), &v(b, i)))
        .fold(0.0, f64::max)
}

/// The chi-square test's false-alarm rate at 3 sigma; twice it bounds the adaptive
/// estimator's escalations on a clean scene (the Wilson-Hilferty tail and the first-order
/// noise model; 41 000 pixels give ~53 alarms, binomial scatter 14 %).
const FALSE_ALARMS: f64 = 2.0 * 0.00135;

#[test]
fn each_estimator_does_what_it_says_on_a_lambertian_set() {
    let set = &sets().lambertian;
    let n = (W * H) as f64;
    for estimator in ["ls", "robust", "adaptive"] {
        let (report, _dir) = solve(set, &["--estimator", estimator]);
        assert_eq!(report["options"]["estimator"], estimator);
        assert_eq!(count(&report, "pixels", "solved"), (W * H) as u64);
        let (e, p) = (mean_error(&report), predicted(&report));
        let escalated = report["escalated"].as_u64().unwrap() as f64;
        match estimator {
            // 41k pixels: the mean's sampling error is ~0.5 %, the first-order model's ~5 %.
            "ls" => {
                assert!((e / p - 1.0).abs() < 0.1, "ls: {e} vs predicted {p}");
                assert_eq!(escalated, 0.0);
                assert_eq!(count(&report, "fits", "robust"), 0);
            }
            // The robust fit runs everywhere; on clean data it keeps every light that agrees
            // and is the weighted (noise-optimal) fit, never worse than least squares.
            "robust" => {
                assert_eq!(escalated, n);
                assert!(e < 1.1 * p, "robust: {e} vs predicted {p}");
            }
            _ => {
                assert!(
                    escalated / n < FALSE_ALARMS,
                    "adaptive escalated {escalated}"
                );
                assert!((e / p - 1.0).abs() < 0.1, "adaptive: {e} vs predicted {p}");
            }
        }
    }
}

/// `--model-error` adds variance to both tests, so it can only pass more pixels: fewer
/// escalations, never more; a negative fraction is refused with the option's name.
#[test]
fn model_error_widens_the_tests() {
    let set = &sets().hard;
    let (plain, _a) = solve(set, &[]);
    let (widened, _b) = solve(set, &["--model-error", "0.05"]);
    assert_eq!(widened["options"]["robust"]["relative_model_error"], 0.05);
    let escalated = |r: &Value| r["escalated"].as_u64().unwrap();
    assert!(escalated(&plain) > 0);
    assert!(
        escalated(&widened) < escalated(&plain),
        "{} vs {}",
        escalated(&widened),
        escalated(&plain)
    );
    // A negative fraction is a usage error (exit 2), caught while the arguments are parsed.
    let bad = psscan(&[
        "solve",
        s(set),
        "--out",
        s(&_a.path().join("bad")),
        "--model-error=-0.1",
    ]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(stderr(&bad).contains("--model-error"), "{}", stderr(&bad));
}

#[test]
fn sheen_fit_halves_the_error_on_shadows_and_sheen() {
    let set = &sets().hard;
    let (ls, _a) = solve(set, &["--estimator", "ls"]);
    let (fit, _b) = solve(set, &["--sheen-fit", "0.35", "0.4", "4"]);
    let (plain, _c) = solve(set, &[]);
    assert_eq!(fit["options"]["robust"]["sheen"]["alpha"], 0.4);
    assert!(plain["options"]["robust"]["sheen"].is_null());
    // The lobe given is the renderer's own: fitting it removes its bias (issue 6's 50 %).
    let (e_ls, e_fit) = (mean_error(&ls), mean_error(&fit));
    assert!(e_fit < 0.5 * e_ls, "sheen fit {e_fit} vs ls {e_ls}");
    assert_eq!(fit["sheen_everywhere"], true);
    assert!(count(&fit, "fits", "sheen") > 0);
    assert_eq!(count(&plain, "fits", "sheen"), 0);
    // A lobe that is not a lobe is refused with the reason.
    assert_refused(
        set,
        &_a.path().join("bad"),
        &["--sheen-fit", "1.5", "0.4", "4"],
        "f0",
    );
}

#[test]
fn precision_and_tiles_stay_within_their_tolerance() {
    let set = &sets().lambertian;
    let (exact, exact_dir) = solve(set, &["--estimator", "ls", "--precision", "f64"]);
    let exact_n = normals(exact_dir.path());
    let tolerance = 0.01;
    for estimator in ["ls", "adaptive"] {
        let (fast, fast_dir) = solve(
            set,
            &[
                "--estimator",
                estimator,
                "--precision",
                "f32",
                "--tile-tolerance",
                "0.01",
            ],
        );
        assert_eq!(fast["options"]["precision"], "f32");
        assert_eq!(fast["options"]["tile_tolerance_deg"], tolerance);
        assert_eq!(count(&fast, "pixels", "solved"), (W * H) as u64);
        // Tiles move no normal by more than the tolerance, f32 adds ~1e-4 deg (src/solve,
        // tests_fast), and the normal maps are stored as f32 (1e-5 deg). The adaptive
        // estimator also re-solves the pixels its test escalates (the false alarms).
        let mut worse = 0;
        let fast_n = normals(fast_dir.path());
        for i in 0..W * H {
            let v = |n: &[psscan::plane::Plane; 3]| {
                nalgebra::Vector3::new(n[0].data[i], n[1].data[i], n[2].data[i]).cast::<f64>()
            };
            if psscan::eval::angle_deg(&v(&fast_n), &v(&exact_n)) > tolerance + 2e-4 {
                worse += 1;
            }
        }
        let allowed = if estimator == "ls" {
            0.0
        } else {
            FALSE_ALARMS * (W * H) as f64
        };
        assert!(worse as f64 <= allowed, "{estimator}: {worse} pixels moved");
        // The means against truth differ by at most the largest move (triangle inequality).
        if estimator == "ls" {
            let d = (mean_error(&fast) - mean_error(&exact)).abs();
            assert!(d <= tolerance + 2e-4, "{d}");
        }
    }
    // The robust estimator runs the exact kernel everywhere: the streaming options are refused.
    assert_refused(
        set,
        &exact_dir.path().join("robust"),
        &["--estimator", "robust", "--precision", "f32"],
        "--estimator adaptive",
    );
    let _ = exact;
}

#[test]
fn normal_only_gives_the_same_normals_and_a_grey_albedo() {
    let set = &sets().lambertian;
    let (full, full_dir) = solve(set, &["--estimator", "ls"]);
    let (only, only_dir) = solve(set, &["--estimator", "ls", "--normal-only"]);
    assert_eq!(only["options"]["normal_only"], true);
    // The luminance solve is the same solve: normals agree to the f32 storage (and the
    // residual and predicted error with them).
    let moved = max_angle(&normals(full_dir.path()), &normals(only_dir.path()));
    assert!(moved < 1e-3, "{moved} deg");
    assert!((mean_error(&full) - mean_error(&only)).abs() < 1e-3);
    let albedo = psscan::io::read_exr(&only_dir.path().join("maps/albedo.exr"), &["R", "G", "B"])
        .expect("albedo.exr");
    for i in 0..W * H {
        assert_eq!(albedo[0].data[i], albedo[1].data[i]);
        assert_eq!(albedo[1].data[i], albedo[2].data[i]);
    }
}

#[test]
fn roi_bin_and_background_limit_the_work() {
    let set = &sets().lambertian;
    let (whole, whole_dir) = solve(set, &["--estimator", "ls"]);
    // A rectangle: only its pixels, with the normals the whole solve has there (each pixel
    // keeps its position under the lights).
    let (roi, roi_dir) = solve(set, &["--estimator", "ls", "--roi", "32,16,64,48"]);
    assert_eq!(
        (roi["width"].as_u64(), roi["height"].as_u64()),
        (Some(64), Some(48))
    );
    assert_eq!(count(&roi, "pixels", "solved"), 64 * 48);
    let a = normals(whole_dir.path());
    let b = normals(roi_dir.path());
    let mut worst: f64 = 0.0;
    for y in 0..48 {
        for x in 0..64 {
            let i = (y + 16) * W + x + 32;
            let j = y * 64 + x;
            let v = |n: &[psscan::plane::Plane; 3], k: usize| {
                nalgebra::Vector3::new(n[0].data[k], n[1].data[k], n[2].data[k]).cast::<f64>()
            };
            worst = worst.max(psscan::eval::angle_deg(&v(&a, i), &v(&b, j)));
        }
    }
    // Both are the default kernel, each within its stated tolerance of the exact kernel's
    // normals (a rectangle gets its own tile grid): at most twice it apart (the scene's light
    // matrices are conditioned far better than 10).
    let tolerance = 2.0 * psscan::solve::default_kernel_tolerance_deg(10.0);
    assert!(worst < tolerance, "roi normals moved {worst} deg");

    // 2x2 binning: a quarter of the pixels, each the mean of four samples, so the noise
    // variance is a quarter and the predicted error half of the full-resolution one (same
    // signal; 10k pixels against 41k). The measured error is not compared: at this sampling
    // (16 sensor pixels apart) a bin spans thread-scale relief and averages four normals.
    let (binned, _b) = solve(set, &["--estimator", "ls", "--bin", "2"]);
    assert_eq!(
        (binned["width"].as_u64(), binned["height"].as_u64()),
        (Some(W as u64 / 2), Some(H as u64 / 2))
    );
    assert_eq!(count(&binned, "pixels", "solved"), (W * H / 4) as u64);
    let ratio = predicted(&binned) / predicted(&whole);
    assert!(ratio > 0.45 && ratio < 0.55, "{ratio}");

    // A background mask file: the right half is table, nothing is solved there.
    let mask_path = whole_dir.path().join("mask.png");
    let mask = image::GrayImage::from_fn(W as u32, H as u32, |x, _| {
        image::Luma([if (x as usize) < W / 2 { 255 } else { 0 }])
    });
    mask.save(&mask_path).unwrap();
    let (masked, _m) = solve(set, &["--estimator", "ls", "--background", s(&mask_path)]);
    assert_eq!(count(&masked, "pixels", "solved"), (W * H / 2) as u64);
    assert_eq!(count(&masked, "pixels", "outside_mask"), (W * H / 2) as u64);
    // A mask of the wrong size is refused, naming the file.
    let small = whole_dir.path().join("small.png");
    image::GrayImage::new(8, 8).save(&small).unwrap();
    assert_refused(
        set,
        &whole_dir.path().join("bad"),
        &["--background", s(&small)],
        "small.png",
    );
}

#[test]
fn bench_json_has_every_variant_with_sane_figures() {
    let out_dir = tempfile::tempdir().unwrap();
    let report = json(&psscan(&[
        "bench",
        "--sizes",
        "0.01",
        "--repeats",
        "1",
        "--no-numpy",
        "--out",
        s(out_dir.path()),
        "--json",
    ]));
    let rows = report["result"]["rows"].as_array().unwrap();
    for variant in psscan::bench::variants() {
        let scenes: Vec<&str> = if variant.scenes.is_empty() {
            psscan::bench::SceneKind::ALL
                .iter()
                .map(|k| k.name())
                .collect()
        } else {
            variant.scenes.iter().map(|k| k.name()).collect()
        };
        for scene in scenes {
            let row = rows
                .iter()
                .find(|r| r["variant"] == variant.name.as_str() && r["scene"] == scene)
                .unwrap_or_else(|| panic!("{} on {scene} is missing", variant.name));
            let seconds = row["seconds"].as_f64().unwrap();
            let error = row["mean_error_deg"].as_f64().unwrap();
            let solved = row["solved_fraction"].as_f64().unwrap();
            assert!(seconds > 0.0 && seconds.is_finite(), "{row}");
            // Every variant solves every pixel of the synthetic scenes, with an error between
            // the noise's (~0.4 deg) and the distant-light model's (~20 deg).
            assert_eq!(solved, 1.0, "{row}");
            assert!(error > 0.1 && error < 45.0, "{row}");
            let escalated = row["escalated_fraction"].as_f64().unwrap();
            assert!((0.0..=1.0).contains(&escalated), "{row}");
        }
    }
    // The floor is timed, the estimator summary has the 0.01 MP figures.
    assert!(rows.iter().any(|r| r["variant"] == "memory-read floor"));
    let figures = &report["estimators"][0];
    assert!(figures["adaptive_over_ls_time"].as_f64().unwrap() > 0.0);
    let ls = figures["shadows_sheen_ls_error_deg"].as_f64().unwrap();
    let adaptive = figures["shadows_sheen_adaptive_error_deg"]
        .as_f64()
        .unwrap();
    let reduction = figures["error_reduction"].as_f64().unwrap();
    assert!((reduction - (1.0 - adaptive / ls)).abs() < 1e-12);
    for file in ["bench.md", "bench.json", "bench.svg"] {
        assert!(out_dir.path().join(file).is_file(), "{file}");
    }
}
