//! `psscan solve SET... --out DIR` on several sets: each set gets DIR/<set folder name>, a
//! broken set in the middle is named and skipped while the others are solved, the exit code
//! says something failed, `--json` lists every set's outcome, and nothing half-written is left
//! anywhere. Also the RAW-specific errors an operator sees: a corrupt RAW frame, frames shot
//! with different settings, `--resolution half` on a dn16 set.

use std::path::Path;
use std::process::{Command, Output};

use psscan::capture::Manifest;
use psscan::fsutil::sha256_hex;
use serde_json::Value;

fn psscan(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_psscan"))
        .args(args)
        .output()
        .expect("psscan runs")
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

fn path_str(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn synth(dir: &Path, encoding: &str) {
    let out = psscan(&[
        "synth",
        "--out",
        path_str(dir),
        "--width",
        "64",
        "--height",
        "48",
        "--encoding",
        encoding,
        "-q",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
}

/// Replaces a frame's bytes and records the new SHA-256, so only the decoder can object.
fn replace_frame(set: &Path, file: &str, bytes: &[u8]) {
    std::fs::write(set.join(file), bytes).unwrap();
    let path = set.join("manifest.toml");
    let mut manifest = Manifest::parse(&std::fs::read_to_string(&path).unwrap(), &path).unwrap();
    for f in &mut manifest.frames {
        if f.file == file {
            f.sha256 = sha256_hex(bytes);
        }
    }
    std::fs::write(&path, manifest.to_toml_string()).unwrap();
}

/// Every entry under `dir`, recursively, as paths relative to it.
fn listing(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            out.push(p.strip_prefix(dir).unwrap().display().to_string());
            if p.is_dir() {
                stack.push(p);
            }
        }
    }
    out.sort();
    out
}

#[test]
#[ignore = "reads ../shared/data: run by make eval"]
fn a_batch_with_a_broken_set_solves_the_others_and_names_it() {
    let tmp = tempfile::tempdir().unwrap();
    let sets = tmp.path().join("sets");
    synth(&sets.join("first"), "dng");
    synth(&sets.join("broken"), "dng");
    synth(&sets.join("last"), "dn16");
    // A truncated RAW frame, with a matching SHA-256: the decoder has to catch it.
    let frame = std::fs::read(sets.join("broken/L04.dng")).unwrap();
    replace_frame(&sets.join("broken"), "L04.dng", &frame[..frame.len() / 3]);
    let bunny = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/bunny-diligent/bunny_lambert_noshadow");
    let (first, broken, last) = (sets.join("first"), sets.join("broken"), sets.join("last"));
    let out = tmp.path().join("maps");
    let args = [
        "solve",
        path_str(&first),
        path_str(&broken),
        path_str(&bunny),
        path_str(&last),
        "--out",
        path_str(&out),
        "--json",
        "-q",
        // The DiLiGenT bunny's figure below is least squares' (see tests/diligent.rs).
        "--estimator",
        "ls",
    ];
    let run = psscan(&args);
    assert_eq!(run.status.code(), Some(1), "{}", stderr(&run));
    assert!(
        stderr(&run).contains("1 of 4 sets failed"),
        "{}",
        stderr(&run)
    );
    let summary: Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(
        (summary["solved"].as_u64(), summary["failed"].as_u64()),
        (Some(3), Some(1))
    );
    let outcomes = summary["sets"].as_array().unwrap();
    let status: Vec<&str> = outcomes
        .iter()
        .map(|o| o["status"].as_str().unwrap())
        .collect();
    assert_eq!(status, ["solved", "failed", "solved", "solved"]);
    let error = outcomes[1]["error"].as_str().unwrap();
    assert!(error.contains("L04.dng"), "{error}");
    assert_eq!(outcomes[2]["kind"], "diligent");
    assert!(outcomes[2]["summary"]["normal_error_deg"].as_f64().unwrap() < 0.01);
    assert!(outcomes[0]["summary"]["normal_error_deg"]
        .as_f64()
        .is_some());

    // Each solved set has its whole output under its own name; the broken one has nothing,
    // and no temporary folder is left.
    let names = listing(&out);
    for set in ["first", "bunny_lambert_noshadow", "last"] {
        for file in ["report.json", "normal.png", "albedo.exr", "confidence.exr"] {
            assert!(
                names.contains(&format!("{set}/{file}")),
                "{set}/{file} in {names:?}"
            );
        }
    }
    assert!(names.iter().all(|n| !n.starts_with("broken")), "{names:?}");
    assert!(
        names
            .iter()
            .all(|n| !n.contains(".partial-") && !n.contains(".old-")),
        "{names:?}"
    );

    // Again without --force: every solved set is refused, nothing changes.
    let before = std::fs::read(out.join("first/report.json")).unwrap();
    let again = psscan(&args);
    assert_eq!(again.status.code(), Some(1));
    let summary: Value = serde_json::from_slice(&again.stdout).unwrap();
    assert_eq!(summary["solved"], 0);
    assert!(summary["sets"][0]["error"]
        .as_str()
        .unwrap()
        .contains("--force"));
    assert_eq!(
        std::fs::read(out.join("first/report.json")).unwrap(),
        before
    );

    // With --force the solved sets are replaced whole.
    let mut forced = args.to_vec();
    forced.push("--force");
    let run = psscan(&forced);
    assert_eq!(run.status.code(), Some(1));
    let summary: Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(summary["solved"], 3);
    assert_eq!(listing(&out), names);
}

#[test]
fn sets_with_the_same_folder_name_are_not_solved_into_one_folder() {
    let tmp = tempfile::tempdir().unwrap();
    synth(&tmp.path().join("a/set"), "dn16");
    synth(&tmp.path().join("b/set"), "dn16");
    let out = tmp.path().join("maps");
    let run = psscan(&[
        "solve",
        path_str(&tmp.path().join("a/set")),
        path_str(&tmp.path().join("b/set")),
        "--out",
        path_str(&out),
        "--json",
        "-q",
    ]);
    assert_eq!(run.status.code(), Some(1));
    let summary: Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(summary["sets"][0]["status"], "solved");
    let error = summary["sets"][1]["error"].as_str().unwrap();
    assert!(error.contains("distinct folder names"), "{error}");
}

#[test]
fn raw_sets_solve_at_both_resolutions_and_say_how_they_were_developed() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    synth(&set, "dng");
    for (resolution, width) in [("full", 64), ("half", 32)] {
        let out = tmp.path().join(resolution);
        let run = psscan(&[
            "solve",
            path_str(&set),
            "--out",
            path_str(&out),
            "--resolution",
            resolution,
            "--json",
            "-q",
        ]);
        assert!(run.status.success(), "{}", stderr(&run));
        let report: Value = serde_json::from_slice(&run.stdout).unwrap();
        assert_eq!(report["width"], width);
        let decode = &report["decode"];
        assert_eq!(decode["encoding"], "raw");
        assert_eq!(decode["cfa_pattern"], "RGGB");
        assert_eq!(decode["camera"]["model"], "synthetic camera");
        assert_eq!(decode["camera"]["iso"], 100);
        assert!(decode["dark_frame"]
            .as_str()
            .unwrap()
            .contains("dark.dng subtracted"));
        assert!(decode["undistortion"]
            .as_str()
            .unwrap()
            .contains("not resampled"));
        assert!(
            report["truth"]["normal_error_deg"]["mean"]
                .as_f64()
                .unwrap()
                < 5.0
        );
    }
    // dn16 frames have no CFA to bin.
    let dn16 = tmp.path().join("dn16");
    synth(&dn16, "dn16");
    let run = psscan(&[
        "solve",
        path_str(&dn16),
        "--out",
        path_str(&tmp.path().join("x")),
        "--resolution",
        "half",
        "-q",
    ]);
    assert_eq!(run.status.code(), Some(1));
    assert!(stderr(&run).contains("half resolution"), "{}", stderr(&run));
}

#[test]
fn raw_frames_shot_differently_or_corrupt_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    synth(&set, "dng");
    // A frame from another set shot at another ISO: rewrite L07 with ISO 400 metadata.
    let bytes = std::fs::read(set.join("L07.dng")).unwrap();
    let decoded = psscan::raw::decode_raw(bytes, Path::new("L07.dng")).unwrap();
    let meta = psscan::raw::RawMeta {
        iso: Some(400),
        ..decoded.meta.clone()
    };
    let rig = psscan::rig::Rig::default_rig();
    let odd = psscan::raw::encode_dng(
        &decoded.mosaic,
        &meta,
        rig.sensor.bits,
        rig.sensor.channel_gain,
        psscan::raw::DngStorage::Uncompressed,
    )
    .unwrap();
    replace_frame(&set, "L07.dng", &odd);
    let run = psscan(&[
        "solve",
        path_str(&set),
        "--out",
        path_str(&tmp.path().join("o")),
        "-q",
    ]);
    assert_eq!(run.status.code(), Some(1));
    let err = stderr(&run);
    assert!(
        err.contains("ISO differs") && err.contains("400 in L07.dng"),
        "{err}"
    );
    assert!(!tmp.path().join("o").exists());

    // A zero-length frame.
    replace_frame(&set, "L07.dng", b"");
    let run = psscan(&[
        "solve",
        path_str(&set),
        "--out",
        path_str(&tmp.path().join("o")),
        "-q",
    ]);
    assert_eq!(run.status.code(), Some(1));
    assert!(
        stderr(&run).contains("L07.dng") && stderr(&run).contains("empty"),
        "{}",
        stderr(&run)
    );
    // No panic message reached the operator.
    assert!(!stderr(&run).contains("panicked"), "{}", stderr(&run));
}

/// A batch worker solves each set into the previous set's outputs (`solve_reusing`): the maps
/// of a set solved after another must be byte for byte those of the set solved alone, on the
/// streaming path (which writes every output of every pixel) and on the exact one.
#[test]
fn a_set_solved_after_another_in_a_batch_equals_the_set_solved_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let sets = tmp.path().join("sets");
    for (name, seed) in [("a", "1"), ("b", "2")] {
        let out = psscan(&[
            "synth",
            "--out",
            path_str(&sets.join(name)),
            "--width",
            "64",
            "--height",
            "48",
            "--seed",
            seed,
            "--shadows",
            "-q",
        ]);
        assert!(out.status.success(), "{}", stderr(&out));
    }
    let (set_a, set_b) = (sets.join("a"), sets.join("b"));
    let streaming: &[&str] = &["--precision", "f32", "--tile-tolerance", "0.01"];
    for extra in [streaming, &[]] {
        let batch = tmp.path().join("batch");
        let alone = tmp.path().join("alone");
        let mut args = vec!["solve", "--parallel-sets", "1", "--force", "-q", "--out"];
        args.push(path_str(&batch));
        args.extend([path_str(&set_a), path_str(&set_b)]);
        args.extend(extra);
        let out = psscan(&args);
        assert!(out.status.success(), "{}", stderr(&out));
        let mut args = vec!["solve", "--force", "-q", "--out", path_str(&alone)];
        args.push(path_str(&set_b));
        args.extend(extra);
        let out = psscan(&args);
        assert!(out.status.success(), "{}", stderr(&out));
        for map in ["normal.exr", "albedo.exr", "confidence.exr"] {
            let batched = std::fs::read(batch.join("b").join(map)).unwrap();
            let single = std::fs::read(alone.join(map)).unwrap();
            assert!(batched == single, "{map} differs with {extra:?}");
        }
    }
}
