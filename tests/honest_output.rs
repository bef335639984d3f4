//! Every figure psscan prints is one it computed (issue 13): a predicted error it could not
//! compute is "n/a" (JSON null), a `--normal-only` solve reports no albedo error, a solve where
//! many pixels fail the model test says so and what to try, a binned solve says what its
//! prediction leaves out, and report.json records how the maps were written.

use std::path::{Path, PathBuf};
use std::process::Output;
use std::sync::OnceLock;

mod common;

use common::{json, psscan, s};
use serde_json::Value;

/// A Lambertian set and a shadows + sheen set, 96 x 64 pixels over the whole field.
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
        let base = ["--width", "96", "--height", "64", "--step", "16", "--json"];
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

/// `psscan solve SET --out <fresh> FLAGS`, once with `--json` and once for people: the
/// report and the human summary.
fn solve(set: &Path, flags: &[&str]) -> (Value, String) {
    let out = tempfile::tempdir().unwrap();
    let run = |name: &str, json_flag: &[&str]| -> Output {
        let dir = out.path().join(name);
        psscan(&[&["solve", s(set), "--out", s(&dir), "-q"], json_flag, flags].concat())
    };
    let report = json(&run("json", &["--json"]));
    let human = run("human", &[]);
    assert!(human.status.success());
    (report, String::from_utf8(human.stdout).unwrap())
}

/// Both kernels predict each pixel's error, and agree on it: the default streaming kernel
/// from its sums over the lights, the exact one (`--precision f64`) light by light. (Where it
/// cannot be computed, a DiLiGenT set of unknown noise, it is null and "n/a":
/// `tests/cli_diligent_generated.rs`.)
#[test]
fn both_kernels_predict_the_error_and_agree() {
    let set = &sets().lambertian;
    let (exact, exact_text) = solve(set, &["--precision", "f64"]);
    let exact_mean = exact["predicted_normal_error_deg"]["mean"]
        .as_f64()
        .unwrap();
    assert!(exact_mean > 0.0);
    assert!(
        exact_text.contains(&format!("predicted normal error {exact_mean:.3} deg")),
        "{exact_text}"
    );
    for flags in [
        &[][..],
        &["--precision", "f32"][..],
        &["--tile-tolerance", "0.01"][..],
    ] {
        let (fast, text) = solve(set, flags);
        assert_eq!(fast["options"]["precision"], "f32", "{flags:?}");
        let mean = fast["predicted_normal_error_deg"]["mean"]
            .as_f64()
            .unwrap_or_else(|| panic!("{flags:?}: no predicted error"));
        // f32 rounding and 0.01-degree tiles move the covariance by well under 1e-3.
        assert!(
            (mean - exact_mean).abs() <= 1e-3 * exact_mean,
            "{flags:?}: {mean} vs exact {exact_mean}"
        );
        assert!(
            text.contains(&format!("predicted normal error {mean:.3} deg")),
            "{flags:?}: {text}"
        );
    }
}

#[test]
fn normal_only_reports_no_albedo_error() {
    let set = &sets().lambertian;
    let (full, _) = solve(set, &[]);
    assert!(full["truth"]["albedo_rel_error"]["mean"].as_f64().unwrap() > 0.0);
    let (only, text) = solve(set, &["--normal-only"]);
    assert!(
        only["truth"]["albedo_rel_error"].is_null(),
        "{}",
        only["truth"]
    );
    assert!(only["truth"]["normal_error_deg"]["mean"].as_f64().unwrap() > 0.0);
    assert!(text.contains("albedo error n/a (--normal-only"), "{text}");
    assert!(!text.contains("albedo error mean"), "{text}");
}

/// Share of the solved pixels the adaptive estimator escalated.
fn failed_share(report: &Value) -> f64 {
    report["escalated"].as_f64().unwrap() / report["pixels"]["solved"].as_f64().unwrap()
}

#[test]
fn many_pixels_failing_the_model_test_are_reported_with_what_to_try() {
    let (clean, text) = solve(&sets().lambertian, &[]);
    // Sensor noise alone: the test's false alarms, a fraction of a percent.
    assert!(failed_share(&clean) < 0.05, "{}", failed_share(&clean));
    assert!(clean["warnings"].is_null(), "{}", clean["warnings"]);
    assert!(!text.contains("WARNING"), "{text}");

    let (hard, text) = solve(&sets().hard, &[]);
    let share = failed_share(&hard);
    assert!(share > 0.05, "{share}");
    let warnings = hard["warnings"].as_array().expect("a warning");
    let warning = warnings[0].as_str().unwrap();
    assert!(
        warning.starts_with(&format!(
            "{:.1} % of the solved pixels fail the model test",
            100.0 * share
        )),
        "{warning}"
    );
    for remedy in ["--sheen-fit", "--model-error"] {
        assert!(warning.contains(remedy), "{warning}");
    }
    assert!(
        text.contains("WARNING: ") && text.contains("fail the model test"),
        "{text}"
    );

    // A batch names the warning beside the set it belongs to.
    let out = tempfile::tempdir().unwrap();
    let batch = json(&psscan(&[
        "solve",
        s(&sets().lambertian),
        s(&sets().hard),
        "--out",
        s(out.path()),
        "--json",
        "-q",
    ]));
    let sets = batch["sets"].as_array().unwrap();
    assert!(sets[0]["summary"]["warnings"].is_null(), "{}", sets[0]);
    let warning = sets[1]["summary"]["warnings"][0].as_str().unwrap();
    assert!(warning.contains("fail the model test"), "{warning}");
}

/// 2x2 binning of RAW frames sums four CFA sites with their own normals; where some face a
/// light and some face away, no single normal explains the sum. On a noise-free Lambertian
/// set (no cast shadows, no sheen) that is the only departure from the model, so the
/// full-resolution solve passes the test everywhere it is tested, and the half-resolution
/// warning names binning and the full-resolution solve as its remedy.
#[test]
fn a_half_resolution_solve_names_binning_when_many_pixels_fail_the_model_test() {
    let dir = tempfile::tempdir().unwrap();
    let set = dir.path().join("dng");
    json(&psscan(&[
        "synth",
        "--out",
        s(&set),
        "--width",
        "192",
        "--height",
        "128",
        "--step",
        "16",
        "--encoding",
        "dng",
        "--noise-free",
        "--json",
    ]));
    let (full, _) = solve(&set, &[]);
    assert!(failed_share(&full) < 0.05, "{}", failed_share(&full));
    assert!(full["warnings"].is_null(), "{}", full["warnings"]);

    let (half, text) = solve(&set, &["--resolution", "half"]);
    assert!(failed_share(&half) > 0.05, "{}", failed_share(&half));
    let warning = half["warnings"][0].as_str().expect("a warning");
    assert!(
        warning.contains("each pixel sums a 2x2 cell of CFA sites"),
        "{warning}"
    );
    assert!(warning.contains("--resolution full"), "{warning}");
    assert!(text.contains("--resolution full"), "{text}");
}

#[test]
fn a_binned_solve_says_its_prediction_covers_noise_only() {
    let set = &sets().lambertian;
    let (whole, _) = solve(set, &["--estimator", "ls"]);
    let (binned, text) = solve(set, &["--estimator", "ls", "--bin", "2"]);
    // A mean of four: a quarter of the variance, half the predicted error.
    let ratio = binned["predicted_normal_error_deg"]["mean"]
        .as_f64()
        .unwrap()
        / whole["predicted_normal_error_deg"]["mean"]
            .as_f64()
            .unwrap();
    assert!((ratio - 0.5).abs() < 0.05, "{ratio}");
    let warnings = binned["warnings"].as_array().expect("a warning");
    assert!(
        warnings.iter().any(|w| w
            .as_str()
            .unwrap()
            .starts_with("binned 2x2: the predicted error covers")),
        "{warnings:?}"
    );
    assert!(text.contains("WARNING: binned 2x2"), "{text}");
    assert!(whole["warnings"].is_null());
}

#[test]
fn the_report_records_how_the_maps_were_written() {
    let set = &sets().lambertian;
    let (plain, _) = solve(set, &[]);
    assert_eq!(plain["maps"]["normal_convention"], "opengl");
    // Recorded once: readers (the page, derive) take it from `maps`.
    assert!(plain.get("normal_convention").is_none(), "{plain}");
    assert_eq!(plain["maps"]["png"], true);
    assert_eq!(plain["maps"]["exr"], true);
    let (dx, _) = solve(
        set,
        &[
            "--directx",
            "--no-png",
            "--estimator",
            "ls",
            "--light-model",
            "distant",
        ],
    );
    assert_eq!(dx["maps"]["normal_convention"], "directx");
    assert_eq!(dx["maps"]["png"], false);
    assert_eq!(dx["options"]["estimator"], "ls");
    assert_eq!(dx["options"]["light_model"], "distant");
    // The same record in the file next to the maps.
    let out = tempfile::tempdir().unwrap();
    let dir = out.path().join("dx");
    json(&psscan(&[
        "solve",
        s(set),
        "--out",
        s(&dir),
        "--directx",
        "-q",
        "--json",
    ]));
    let written: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    assert_eq!(written["maps"]["normal_convention"], "directx");
    assert_eq!(written["maps"]["png"], true);
}

/// A DiLiGenT-layout set written here: a 16 x 16 Lambertian plane tilted toward +x (normal
/// (0.2, 0, 0.98)), albedo 0.5, under six distant lights.
fn write_diligent_set(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    let lights: [[f64; 3]; 6] = [
        [0.0, 0.0, 1.0],
        [0.5, 0.0, 0.866],
        [-0.5, 0.0, 0.866],
        [0.0, 0.5, 0.866],
        [0.0, -0.5, 0.866],
        [0.35, 0.35, 0.866],
    ];
    let n = {
        let v = [0.2f64, 0.0, 0.98];
        let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        v.map(|c| c / len)
    };
    let (mut names, mut directions, mut intensities) =
        (String::new(), String::new(), String::new());
    for (k, l) in lights.iter().enumerate() {
        let len = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt();
        let l = l.map(|c| c / len);
        let shade = 0.5 * (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]);
        let value = (shade * 65535.0).round() as u16;
        let name = format!("{:03}.png", k + 1);
        image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::from_pixel(16, 16, image::Rgb([value; 3]))
            .save(dir.join(&name))
            .unwrap();
        names.push_str(&format!("{name}\n"));
        directions.push_str(&format!("{} {} {}\n", l[0], l[1], l[2]));
        intensities.push_str("1 1 1\n");
    }
    std::fs::write(dir.join("filenames.txt"), names).unwrap();
    std::fs::write(dir.join("light_directions.txt"), directions).unwrap();
    std::fs::write(dir.join("light_intensities.txt"), intensities).unwrap();
}

#[test]
fn a_diligent_set_has_no_predicted_error() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("plane");
    write_diligent_set(&set);
    // The benchmark's noise is unknown, so there is no prediction; the solve itself works.
    let (report, text) = solve(&set, &["--estimator", "ls"]);
    assert_eq!(report["pixels"]["solved"], 256);
    assert!(report["predicted_normal_error_deg"]["mean"].is_null());
    assert!(text.contains("predicted normal error n/a"), "{text}");
}
