//! A command camera (`--camera cmd:TEMPLATE`) that returns frames other than the manifest
//! records, or the same photograph again, stops the capture at that frame with the reason,
//! and every frame before it stays in the set as it was. The issue saw a command camera
//! recorded as `encoding = "raw"` at 4928x3264 for 320x240 PNGs, and eleven identical frames
//! kept. The camera here is a small shell script that copies prepared files, driven through
//! the CLI against the LED firmware in its emulator.

use std::path::{Path, PathBuf};

use psscan::capture::CaptureSet;
use psscan::raw::{encode_dng, DngStorage, Mosaic, RawMeta};
use psscan::sim::emulator::{Emulator, EmulatorFiles};

mod common;

use common::{psscan, s, stderr};

fn emulator(dir: &Path) -> Emulator {
    let files = EmulatorFiles::locate().expect("make -C firmware all sim");
    Emulator::start(&files, &dir.join("pins.log")).unwrap()
}

/// A small DNG whose samples depend on `seed` (so every file differs), `w x h` samples.
fn dng(seed: usize, w: usize, h: usize) -> Vec<u8> {
    let mosaic = Mosaic {
        width: w,
        height: h,
        pattern: Mosaic::parse_pattern("RGGB").unwrap(),
        black: [[600.0; 2]; 2],
        white: 15600.0,
        samples: (0..w * h)
            .map(|i| (600 + (i * 7919 + seed * 104729) % 15001) as u16)
            .collect(),
    };
    let meta = RawMeta {
        make: "psscan".into(),
        model: "test".into(),
        width: w,
        height: h,
        iso: Some(100),
        shutter_s: Some(0.1),
        aperture: Some(8.0),
    };
    encode_dng(&mosaic, &meta, 14, [0.55, 1.0, 0.72], DngStorage::Lossless).unwrap()
}

/// A camera command that copies `dir/shot<n>.<ext>` for its n-th shot (0 = the dark frame).
fn copying_camera(dir: &Path, ext: &str) -> String {
    let counter = dir.join("count");
    format!(
        "cmd:sh -c 'n=$(cat {c} 2>/dev/null || echo 0); echo $((n+1)) > {c}; \
         cp {d}/shot$n.{ext} \"$1\"' sh {{out}}",
        c = s(&counter),
        d = s(dir),
    )
}

fn capture(set: &Path, pty: &str, camera: &str, ext: &str) -> (Option<i32>, String) {
    let out = psscan(&[
        "capture",
        "--out",
        s(set),
        "--port",
        pty,
        "--camera",
        camera,
        "--frame-ext",
        ext,
        "--settle-ms",
        "5",
    ]);
    (out.status.code(), stderr(&out))
}

/// The frames a stopped capture kept, with their bytes checked against what the camera gave.
fn kept(set: &Path, shots: &Path, ext: &str) -> Vec<String> {
    let kept = CaptureSet::open(set, None).unwrap();
    for (n, f) in kept.manifest.frames.iter().enumerate() {
        let stored = std::fs::read(set.join(&f.file)).unwrap();
        let given = std::fs::read(shots.join(format!("shot{n}.{ext}"))).unwrap();
        assert!(stored == given, "{} is not the camera's shot {n}", f.file);
        assert_eq!(f.sha256, psscan::fsutil::sha256_hex(&stored));
    }
    kept.manifest
        .frames
        .iter()
        .map(|f| f.file.clone())
        .collect()
}

#[test]
fn pngs_from_a_camera_recorded_as_raw_stop_at_the_first_frame() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let synth = t.join("synth");
    let out = psscan(&[
        "synth",
        "--out",
        s(&synth),
        "--width",
        "320",
        "--height",
        "240",
        "-q",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let shots = t.join("shots");
    std::fs::create_dir_all(&shots).unwrap();
    std::fs::copy(synth.join("dark.png"), shots.join("shot0.png")).unwrap();
    for k in 0..10 {
        std::fs::copy(
            synth.join(format!("L{k:02}.png")),
            shots.join(format!("shot{}.png", k + 1)),
        )
        .unwrap();
    }
    let emu = emulator(t);
    let set = t.join("set");
    let (code, err) = capture(&set, emu.pty(), &copying_camera(&shots, "png"), "png");
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("dark.png is a 320x240 PNG image")
            && err.contains("the manifest records raw frames of 4928x3264"),
        "{err}"
    );
    assert!(err.contains("all LEDs are off"), "{err}");
    assert!(kept(&set, &shots, "png").is_empty());
    assert!(emu.pin_log().lit().unwrap().is_empty());
}

#[test]
fn the_same_photograph_twice_stops_at_the_second_and_keeps_the_first() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let shots = t.join("shots");
    std::fs::create_dir_all(&shots).unwrap();
    let same = dng(1, 64, 48);
    for n in 0..11 {
        // Two distinct frames, then the camera keeps handing back the last one.
        let bytes = if n < 2 { dng(n, 64, 48) } else { same.clone() };
        std::fs::write(shots.join(format!("shot{n}.dng")), bytes).unwrap();
    }
    let emu = emulator(t);
    let set = t.join("set");
    let (code, err) = capture(&set, emu.pty(), &copying_camera(&shots, "dng"), "dng");
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("frame L01 (LED 1)")
            && err.contains("L01.dng is byte-for-byte the same photograph as L00.dng"),
        "{err}"
    );
    assert_eq!(kept(&set, &shots, "dng"), ["dark.dng", "L00.dng"]);
    assert!(emu.pin_log().lit().unwrap().is_empty());
}

#[test]
fn a_raw_frame_of_another_size_stops_at_that_frame() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let shots: PathBuf = t.join("shots");
    std::fs::create_dir_all(&shots).unwrap();
    for n in 0..11 {
        let (w, h) = if n == 3 { (48, 48) } else { (64, 48) };
        std::fs::write(shots.join(format!("shot{n}.dng")), dng(n, w, h)).unwrap();
    }
    let emu = emulator(t);
    let set = t.join("set");
    let (code, err) = capture(&set, emu.pty(), &copying_camera(&shots, "dng"), "dng");
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("frame L02 (LED 2)")
            && err.contains(
                "L02.dng is a camera RAW file of 48x48, the set's earlier RAW frames 64x48"
            ),
        "{err}"
    );
    assert_eq!(
        kept(&set, &shots, "dng"),
        ["dark.dng", "L00.dng", "L01.dng"]
    );
}
