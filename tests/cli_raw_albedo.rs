//! Issue 13: full-resolution RAW albedo through the CLI. `psscan synth --encoding dng` renders
//! the demo textile to DNG frames; `psscan solve` at full resolution develops them with the
//! stack demosaic (site albedos fitted under the rig's LEDs, colour ratios interpolated along
//! the pixel's own material) and compares the maps with the set's ground truth.

use std::path::Path;
use std::process::Command;

use serde_json::Value;

fn psscan(args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_psscan"))
        .args(args)
        .output()
        .expect("psscan runs");
    assert!(
        out.status.success(),
        "psscan {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Synthesises the demo scene as DNG frames, solves it with `extra` arguments and returns
/// report.json's `truth` comparison.
fn solve_dng(dir: &Path, synth_extra: &[&str], solve_extra: &[&str]) -> Value {
    let set = dir.join("set");
    let out = dir.join("out");
    let (set, out) = (set.to_str().unwrap(), out.to_str().unwrap());
    let mut synth = vec![
        "synth",
        "--out",
        set,
        "--encoding",
        "dng",
        "--width",
        "320",
        "--height",
        "240",
    ];
    synth.extend_from_slice(synth_extra);
    psscan(&synth);
    let mut solve = vec!["-q", "solve", set, "--out", out, "--json"];
    solve.extend_from_slice(solve_extra);
    psscan(&solve);
    let report: Value =
        serde_json::from_slice(&std::fs::read(dir.join("out/report.json")).unwrap()).unwrap();
    report["truth"].clone()
}

/// The target: full-resolution albedo within 2 % mean of the truth, as the 16-bit PNG
/// frames of the same scene give (their error is the sensor noise and quantisation, under
/// 1 %; a demosaic adds its colour-ratio error on top). Not met yet: the albedo-domain,
/// material-following demosaic brings the mean from about 17 % to about 4 %, and averaging
/// each pixel's log chroma over the pixels of the same chroma around it (a joint bilateral
/// filter whose range is the chroma's measured noise) to 3.0 % (median 0.8 %). What is left
/// is mostly the 1 % of missing channels where the pixel took the other material's colour:
/// dark channels (albedo about 0.05) next to a thread or gap edge whose own channel is the
/// same on both sides, so only the normal tells them apart. Run with `--ignored`.
#[test]
#[ignore = "issue 13 target not met yet: full-resolution RAW albedo mean error is about 3 %"]
fn full_resolution_dng_albedo_is_within_two_percent_mean_of_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let truth = solve_dng(dir.path(), &[], &[]);
    let mean = truth["albedo_rel_error"]["mean"].as_f64().unwrap();
    assert!(mean < 0.02, "albedo mean relative error {mean}");
}
