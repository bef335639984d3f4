//! End-to-end tests of the `psscan` binary: synth -> solve -> maps, the demo, `--json`
//! output, exit codes, and the errors an operator sees for bad input.

use std::path::Path;

mod common;

use common::{json, psscan, s, stderr};
use serde_json::Value;

/// A small synthetic set covering the whole field (every 16th sensor pixel).
fn synth_set(dir: &Path) {
    let out = psscan(&[
        "synth",
        "--out",
        s(dir),
        "--width",
        "256",
        "--height",
        "160",
        "--step",
        "16",
        "--json",
    ]);
    let summary = json(&out);
    assert_eq!(summary["lights"], 10);
    assert!(dir.join("manifest.toml").is_file());
    for k in 0..10 {
        assert!(dir.join(format!("L{k:02}.png")).is_file());
    }
    assert!(dir.join("dark.png").is_file() && dir.join("truth/normal.exr").is_file());
}

#[test]
fn synth_then_solve_reports_errors_that_match_the_noise_model() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    let maps = tmp.path().join("maps");
    synth_set(&set);
    let report = json(&psscan(&["solve", s(&set), "--out", s(&maps), "--json"]));
    let measured = report["truth"]["normal_error_deg"]["mean"]
        .as_f64()
        .unwrap();
    let predicted = report["predicted_normal_error_deg"]["mean"]
        .as_f64()
        .unwrap();
    // 41k pixels: the mean's sampling error is about 0.5 %, far inside the 10 % model bound.
    assert!(
        (measured / predicted - 1.0).abs() < 0.1,
        "measured {measured}, predicted {predicted}"
    );
    assert_eq!(report["pixels"]["solved"], 256 * 160);
    for name in [
        "normal.png",
        "normal.exr",
        "albedo.png",
        "albedo.exr",
        "confidence.exr",
        "report.json",
    ] {
        assert!(maps.join(name).is_file(), "{name} missing");
    }
    let written: Value =
        serde_json::from_str(&std::fs::read_to_string(maps.join("report.json")).unwrap()).unwrap();
    assert_eq!(written["truth"], report["truth"]);

    // An existing solve is not overwritten without --force.
    let again = psscan(&["solve", s(&set), "--out", s(&maps)]);
    assert_eq!(again.status.code(), Some(1));
    assert!(stderr(&again).contains("--force"), "{}", stderr(&again));
    let forced = psscan(&["solve", s(&set), "--out", s(&maps), "--force", "-q"]);
    assert!(forced.status.success(), "{}", stderr(&forced));
}

#[test]
fn normal_png_matches_the_exr_and_directx_flips_green() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    synth_set(&set);
    let gl = tmp.path().join("gl");
    let dx = tmp.path().join("dx");
    json(&psscan(&["solve", s(&set), "--out", s(&gl), "--json"]));
    json(&psscan(&[
        "solve",
        s(&set),
        "--out",
        s(&dx),
        "--directx",
        "--json",
    ]));
    let png_gl = image::open(gl.join("normal.png")).unwrap().into_rgb16();
    let png_dx = image::open(dx.join("normal.png")).unwrap().into_rgb16();
    let exr = psscan::io::read_exr(&gl.join("normal.exr"), &["R", "G", "B"]).unwrap();
    let decode = |v: u16| v as f32 / 65535.0 * 2.0 - 1.0;
    for (i, (a, b)) in png_gl.pixels().zip(png_dx.pixels()).enumerate() {
        for c in 0..3 {
            assert!((decode(a[c]) - exr[c].data[i]).abs() <= 1.0 / 65535.0 + 1e-6);
        }
        assert_eq!(a[0], b[0]);
        assert_eq!(a[2], b[2]);
        // G is mirrored around the code for 0 (32767.5).
        assert!((a[1] as i32 + b[1] as i32 - 65535).abs() <= 1);
    }
    // A flat-on-average textile: the mean normal points up.
    let mean_z = exr[2].data.iter().map(|&v| v as f64).sum::<f64>() / exr[2].len() as f64;
    assert!(mean_z > 0.8, "{mean_z}");
}

#[test]
fn demo_json_has_the_documented_fields_and_writes_every_map() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let summary = json(&psscan(&[
        "demo",
        "--out",
        s(&out),
        "--width",
        "320",
        "--height",
        "240",
        "--json",
    ]));
    for stat in ["mean", "median", "p95"] {
        assert!(summary["normal_error_deg"][stat].as_f64().unwrap() > 0.0);
    }
    assert!(
        summary["predicted_normal_error_deg"]["mean"]
            .as_f64()
            .unwrap()
            > 0.0
    );
    assert!(summary["albedo_rel_error"]["mean"].as_f64().unwrap() < 0.05);
    assert!(summary["timings_s"]["total"].as_f64().unwrap() > 0.0);
    let outputs = &summary["paths"]["outputs"];
    for key in [
        "normal_png",
        "normal_exr",
        "albedo_png",
        "albedo_exr",
        "confidence_exr",
    ] {
        let p = outputs[key].as_str().unwrap();
        assert!(Path::new(p).is_file(), "{key}: {p}");
    }
    assert!(Path::new(summary["paths"]["report"].as_str().unwrap()).is_file());
    // Running the demo again replaces its own output without complaint.
    let again = psscan(&[
        "demo",
        "--out",
        s(&out),
        "--width",
        "64",
        "--height",
        "48",
        "-q",
    ]);
    assert!(again.status.success(), "{}", stderr(&again));
    assert!(String::from_utf8_lossy(&again.stdout).contains("normal error"));
}

#[test]
fn bad_input_gives_a_clear_error_and_exit_code_1() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("no-such-set");
    let out = psscan(&["solve", s(&missing), "--out", s(&tmp.path().join("o"))]);
    assert_eq!(out.status.code(), Some(1));
    assert!(stderr(&out).contains("no-such-set") && stderr(&out).contains("not a capture set"));

    let set = tmp.path().join("set");
    synth_set(&set);
    // A frame damaged after capture is named.
    let frame = set.join("L03.png");
    let mut bytes = std::fs::read(&frame).unwrap();
    let n = bytes.len();
    bytes[n / 2] ^= 0x40;
    std::fs::write(&frame, bytes).unwrap();
    let out = psscan(&["solve", s(&set), "--out", s(&tmp.path().join("o"))]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        stderr(&out).contains("L03.png") && stderr(&out).contains("SHA-256"),
        "{}",
        stderr(&out)
    );
    // Nothing was written for the failed solve.
    assert!(!tmp.path().join("o").join("report.json").exists());

    // A rig with a field error is named.
    let rig = tmp.path().join("rig.toml");
    std::fs::write(
        &rig,
        psscan::rig::DEFAULT_RIG_TOML.replace("fx = 7322.0", "fx = -1.0"),
    )
    .unwrap();
    let out = psscan(&[
        "synth",
        "--out",
        s(&tmp.path().join("s2")),
        "--rig",
        s(&rig),
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(stderr(&out).contains("camera.fx"), "{}", stderr(&out));

    // Usage errors are exit code 2.
    assert_eq!(psscan(&["solve"]).status.code(), Some(2));
}

#[test]
fn an_existing_capture_set_is_not_overwritten_without_force() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    synth_set(&set);
    let before = std::fs::read(set.join("manifest.toml")).unwrap();
    let out = psscan(&["synth", "--out", s(&set), "--width", "32", "--height", "32"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(stderr(&out).contains("--force"));
    assert_eq!(std::fs::read(set.join("manifest.toml")).unwrap(), before);
}
