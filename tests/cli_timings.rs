//! `psscan solve`'s whole-command figures: the stage table in `report.json` and `--timings`,
//! `--png-compression`, and the default kernel against the exact one (`--precision f64`)
//! through the CLI, on a small synthetic RAW (DNG) set.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

mod common;

use common::{json, psscan, s, stderr};
use serde_json::Value;

const W: usize = 192;
const H: usize = 128;

/// A small synthetic set, rendered once per encoding (`dng` or `dn16`), noise-free: the tile
/// tolerance bounds how far the interpolated coefficients move the normal of a measurement
/// the model fits (noise adds its residual times the coefficient error).
fn set(encoding: &'static str) -> &'static Path {
    static SETS: OnceLock<(tempfile::TempDir, PathBuf, PathBuf)> = OnceLock::new();
    let sets = SETS.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (W.to_string(), H.to_string());
        let render = |encoding: &str| {
            let path = dir.path().join(encoding);
            json(&psscan(&[
                "synth",
                "--out",
                s(&path),
                "--width",
                &w,
                "--height",
                &h,
                "--step",
                "16",
                "--encoding",
                encoding,
                "--noise-free",
                "--json",
            ]));
            path
        };
        let (dng, dn16) = (render("dng"), render("dn16"));
        (dir, dng, dn16)
    });
    if encoding == "dng" {
        &sets.1
    } else {
        &sets.2
    }
}

fn solve(flags: &[&str]) -> (Value, tempfile::TempDir) {
    solve_set(set("dng"), flags)
}

fn solve_set(set: &Path, flags: &[&str]) -> (Value, tempfile::TempDir) {
    let out = tempfile::tempdir().unwrap();
    let maps = out.path().join("maps");
    let report = json(&psscan(
        &[&["solve", s(set), "--out", s(&maps), "--json"], flags].concat(),
    ));
    (report, out)
}

#[test]
fn the_stage_table_adds_up_to_the_total() {
    let (report, out) = solve(&[]);
    let on_disk: Value = serde_json::from_str(
        &std::fs::read_to_string(out.path().join("maps/report.json")).unwrap(),
    )
    .unwrap();
    for r in [&report, &on_disk] {
        let stages = r["stages"].as_array().expect("a stage table");
        let names: Vec<&str> = stages
            .iter()
            .map(|s| s["stage"].as_str().unwrap())
            .collect();
        for needed in [
            "read",
            "hash check",
            "decode",
            "dark subtraction",
            "demosaic",
            "noise model",
            "solve",
            "write normal.png",
            "write confidence.exr",
            "sync confidence.exr",
            "report",
            "other",
        ] {
            assert!(names.contains(&needed), "no {needed} in {names:?}");
        }
        assert_eq!(names.last(), Some(&"other"));
        let sum: f64 = stages.iter().map(|s| s["seconds"].as_f64().unwrap()).sum();
        let total = r["timings_s"]["total"].as_f64().unwrap();
        assert!(stages.iter().all(|s| s["seconds"].as_f64().unwrap() >= 0.0));
        // Rounding only: JSON keeps f64 to the last bit, the sum has ~25 terms.
        assert!(
            (sum - total).abs() <= 1e-9 * total.max(1.0),
            "{sum} vs {total}"
        );
    }
    // --timings prints the same table.
    let out = tempfile::tempdir().unwrap();
    let output = psscan(&[
        "solve",
        s(set("dng")),
        "--out",
        s(&out.path().join("m")),
        "--timings",
    ]);
    assert!(output.status.success());
    let text = String::from_utf8_lossy(&output.stdout);
    assert!(
        text.contains("where the time went") && text.contains("hash check"),
        "{text}"
    );
}

#[test]
fn png_compression_best_keeps_the_pixels() {
    let (fast, fast_dir) = solve(&[]);
    let (best, best_dir) = solve(&["--png-compression", "best"]);
    for name in ["normal.png", "albedo.png"] {
        let a = std::fs::read(fast_dir.path().join("maps").join(name)).unwrap();
        let b = std::fs::read(best_dir.path().join("maps").join(name)).unwrap();
        assert_ne!(a, b, "{name}: the flag must change the encoding");
        assert!(
            b.len() <= a.len(),
            "{name}: best {} > fast {}",
            b.len(),
            a.len()
        );
        let pa = image::load_from_memory(&a).unwrap().into_rgb16().into_raw();
        let pb = image::load_from_memory(&b).unwrap().into_rgb16().into_raw();
        assert_eq!(pa, pb, "{name}");
    }
    let _ = (fast, best);
    let output = psscan(&[
        "solve",
        s(set("dng")),
        "--out",
        "unused",
        "--png-compression",
        "smallest",
    ]);
    assert_eq!(output.status.code(), Some(2));
}

/// The fast kernel (the default, as `--precision f32` alone: streaming f32, tiles of 0.01
/// degrees) against the exact one (`--precision f64`): the stated per-pixel tolerance
/// (`default_kernel_tolerance_deg` of the pixel's condition number) on the written normal maps
/// (stored as f32: 1e-5 degrees more).
#[test]
fn the_default_kernel_is_within_its_tolerance_of_the_exact_one() {
    for encoding in ["dn16", "dng"] {
        let set = set(encoding);
        let (fast, fast_dir) = solve_set(set, &["--estimator", "ls"]);
        let (exact, exact_dir) = solve_set(set, &["--estimator", "ls", "--precision", "f64"]);
        assert_eq!(fast["options"]["precision"], "f32");
        assert_eq!(fast["options"]["tile_tolerance_deg"], 0.01);
        assert_eq!(exact["options"]["precision"], "f64");
        assert!(exact["options"]["tile_tolerance_deg"].is_null());
        let read = |dir: &Path| {
            psscan::io::read_exr(&dir.join("maps/normal.exr"), &["R", "G", "B"]).unwrap()
        };
        let (a, b) = (read(fast_dir.path()), read(exact_dir.path()));
        let condition = psscan::io::read_exr(
            &exact_dir.path().join("maps/confidence.exr"),
            &["condition"],
        )
        .unwrap();
        let mut worst = 0f64;
        for i in 0..W * H {
            let v = |n: &[psscan::plane::Plane]| {
                nalgebra::Vector3::new(n[0].data[i], n[1].data[i], n[2].data[i]).cast::<f64>()
            };
            let e = psscan::eval::angle_deg(&v(&a), &v(&b));
            let tolerance =
                psscan::solve::default_kernel_tolerance_deg(condition[0].data[i] as f64) + 1e-5;
            assert!(
                e <= tolerance,
                "{encoding} pixel {i}: {e} deg, tol {tolerance}"
            );
            worst = worst.max(e / tolerance);
        }
        assert!(worst > 0.0, "the two kernels cannot agree to the bit");
    }
    // The robust estimator fits with the exact kernel only: asking it for the fast one is
    // refused with what to do instead.
    let out = tempfile::tempdir().unwrap();
    let maps = out.path().join("maps");
    let refused = psscan(&[
        "solve",
        s(set("dng")),
        "--out",
        s(&maps),
        "--estimator",
        "robust",
        "--precision",
        "f32",
    ]);
    assert_eq!(refused.status.code(), Some(1));
    assert!(
        stderr(&refused).contains("exact kernel"),
        "{}",
        stderr(&refused)
    );
    assert!(!maps.exists());
}
