//! A white-sheet LED fit that did not converge or is implausible is refused everywhere: the
//! `calibrate whitesheet` step exits non-zero and records the fit as rejected, `calibrate
//! bundle` refuses it, and `solve` refuses a bundle that holds one. The issue produced such a
//! fit by giving the step a textile capture set (`psscan synth`) as the white sheet's
//! photographs: the LEDs ran 473 mm away from their hand measurements in 50 iterations and
//! the step exited 0. The same here.

use std::path::Path;

mod common;

use common::{psscan, s, stderr};
use psscan::calibration::bundle::{self, Calibration, Parts};
use psscan::calibration::lights::LightFit;
use psscan::calibration::steps::WhiteSheetStep;
use psscan::rig::Rig;

fn synth_textile(dir: &Path) {
    let out = psscan(&[
        "synth",
        "--out",
        s(dir),
        "--width",
        "320",
        "--height",
        "240",
        "-q",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
}

#[test]
fn a_textile_set_as_the_white_sheet_is_rejected_and_no_bundle_takes_it() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let set = t.join("set");
    synth_textile(&set);
    let ws = t.join("ws.toml");
    let out = psscan(&[
        "calibrate",
        "whitesheet",
        "--images",
        s(&set),
        "--step",
        "1",
        "--out",
        s(&ws),
        "-q",
    ]);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("rejected") && err.contains("did not converge") && err.contains("ws.toml"),
        "{err}"
    );
    // Written, but as rejected, with every reason: the fit wandered beyond the rig's
    // tolerance, and its residual is far beyond noise plus the model's accuracy.
    let step: WhiteSheetStep = toml::from_str(&std::fs::read_to_string(&ws).unwrap()).unwrap();
    let reasons = step.lights.problems().join("\n");
    assert!(!step.lights.converged);
    assert!(
        reasons.contains("did not converge")
            && reasons.contains("from the hand measurement")
            && reasons.contains("rms relative residual"),
        "{reasons}"
    );

    // The bundle step refuses it, naming the file and the cause, and writes nothing.
    let bundle_dir = t.join("bundle");
    let out = psscan(&[
        "calibrate",
        "bundle",
        "--whitesheet",
        s(&ws),
        "--out",
        s(&bundle_dir),
    ]);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("ws.toml") && err.contains("rejected"), "{err}");
    assert!(!bundle_dir.exists());

    // A fit that did converge but was edited to say otherwise (or written before fits were
    // judged) is refused too: the bundle step reads `converged`.
    let mut old = step.clone();
    old.lights.rejected_because.clear();
    let old_file = t.join("old.toml");
    std::fs::write(&old_file, toml::to_string(&old).unwrap()).unwrap();
    let out = psscan(&[
        "calibrate",
        "bundle",
        "--whitesheet",
        s(&old_file),
        "--out",
        s(&bundle_dir),
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        stderr(&out).contains("did not converge"),
        "{}",
        stderr(&out)
    );
    assert!(!bundle_dir.exists());

    // A bundle holding a rejected fit (assembled before fits were judged): solve refuses it
    // and writes nothing.
    let holding = t.join("holding");
    write_bundle_with(&holding, &step.lights);
    let solved = t.join("solved");
    let out = psscan(&[
        "solve",
        s(&set),
        "--out",
        s(&solved),
        "--calibration",
        s(&holding),
        "-q",
    ]);
    let err = stderr(&out);
    assert_ne!(out.status.code(), Some(0), "{err}");
    assert!(
        err.contains("calibration.toml") && err.contains("rejected"),
        "{err}"
    );
    assert!(!solved.exists());
}

/// A valid bundle (checksums and all) whose calibration holds `lights`, as an older psscan
/// would have written it: a good bundle first, then its numbers replaced and re-indexed.
fn write_bundle_with(dir: &Path, lights: &LightFit) {
    let rig = Rig::default_rig();
    let mut cal = Calibration {
        sheet_reflectance: Some(0.9),
        ..Calibration::default()
    };
    let parts = Parts {
        calibration: &cal,
        rig: &rig,
        maps: &[],
        gains: None,
    };
    bundle::write_parts(dir, &rig.name, "old", &parts).unwrap();
    cal.lights = Some(lights.clone());
    let numbers = dir.join("calibration.toml");
    std::fs::write(&numbers, toml::to_string_pretty(&cal).unwrap()).unwrap();
    let index_path = dir.join(bundle::INDEX_FILE);
    let mut index: bundle::BundleIndex =
        toml::from_str(&std::fs::read_to_string(&index_path).unwrap()).unwrap();
    index.files.insert(
        "calibration.toml".into(),
        psscan::fsutil::sha256_file(&numbers).unwrap(),
    );
    std::fs::write(&index_path, toml::to_string_pretty(&index).unwrap()).unwrap();
    index.sha256 = bundle::checksum(dir).unwrap();
    std::fs::write(&index_path, toml::to_string_pretty(&index).unwrap()).unwrap();
}
