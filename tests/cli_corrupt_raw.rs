//! A RAW frame whose compressed image data was damaged after capture (and its checksum
//! updated, so the manifest cannot tell) is refused by `solve`, naming the frame: either the
//! guard finds its lossless-JPEG header disagreeing with the container before the decoder
//! runs, or the frame decodes to garbage and the set's checks catch it. The case: a
//! 320x240 synthetic DNG set with a few damaged bytes in one frame solved without a word
//! (albedo error 143 %).

use std::path::Path;

mod common;

use common::{psscan, s, stderr};

/// The first IFD's TileOffsets with their byte counts.
fn tiles(dng: &[u8]) -> Vec<(usize, usize)> {
    let u16_at = |p: usize| u16::from_le_bytes([dng[p], dng[p + 1]]) as usize;
    let u32_at = |p: usize| u32::from_le_bytes(dng[p..p + 4].try_into().unwrap()) as usize;
    let ifd = u32_at(4);
    let (mut offsets, mut counts) = (Vec::new(), Vec::new());
    for e in 0..u16_at(ifd) {
        let entry = ifd + 2 + 12 * e;
        let (tag, n) = (u16_at(entry), u32_at(entry + 4));
        if tag == 324 || tag == 325 {
            let at = if n == 1 { entry + 8 } else { u32_at(entry + 8) };
            let values = (0..n).map(|k| u32_at(at + 4 * k)).collect();
            if tag == 324 {
                offsets = values;
            } else {
                counts = values;
            }
        }
    }
    offsets.into_iter().zip(counts).collect()
}

/// Damages `set/L03.dng` with `damage` and writes its new checksum into the manifest.
fn damage(set: &Path, damage: impl Fn(&mut Vec<u8>, &[(usize, usize)])) {
    let path = set.join("L03.dng");
    let mut bytes = std::fs::read(&path).unwrap();
    let old = psscan::fsutil::sha256_hex(&bytes);
    let segments = tiles(&bytes);
    assert_eq!(segments.len(), 2, "a 320x240 frame in 256x256 tiles");
    damage(&mut bytes, &segments);
    std::fs::write(&path, &bytes).unwrap();
    let manifest = set.join("manifest.toml");
    let text = std::fs::read_to_string(&manifest).unwrap();
    assert!(text.contains(&old));
    let new = psscan::fsutil::sha256_hex(&bytes);
    std::fs::write(&manifest, text.replace(&old, &new)).unwrap();
}

fn synth_dng(dir: &Path) {
    let out = psscan(&[
        "synth",
        "--out",
        s(dir),
        "--encoding",
        "dng",
        "--width",
        "320",
        "--height",
        "240",
        "-q",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
}

fn refused(set: &Path, out_dir: &Path) -> String {
    refused_with(set, out_dir, &[])
}

/// [`refused`], solving with `flags`.
fn refused_with(set: &Path, out_dir: &Path, flags: &[&str]) -> String {
    let out = psscan(&[&["solve", s(set), "--out", s(out_dir), "-q"], flags].concat());
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("L03.dng"), "{err}");
    assert!(!out_dir.exists(), "nothing is written for a refused set");
    let name = out_dir.file_name().unwrap().to_string_lossy().into_owned();
    let parent = out_dir.parent().unwrap();
    let debris: Vec<String> = (std::fs::read_dir(parent).unwrap())
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(&format!("{name}.")))
        .collect();
    assert!(debris.is_empty(), "staging left behind: {debris:?}");
    err
}

#[test]
fn damaged_bytes_in_a_dng_frames_compressed_data_are_refused_naming_the_frame() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let clean = t.join("clean");
    synth_dng(&clean);
    // The clean set solves.
    let out = psscan(&["solve", s(&clean), "--out", s(&t.join("clean-out")), "-q"]);
    assert!(out.status.success(), "{}", stderr(&out));

    // A damaged frame header (the SOF's line count of the first tile): refused before the
    // decoder runs.
    let header = t.join("header");
    synth_dng(&header);
    damage(&header, |b, tiles| {
        let sof = tiles[0].0 + 2;
        assert_eq!(&b[sof..sof + 2], &[0xFF, 0xC3]);
        b[sof + 5] ^= 0xFF;
    });
    let err = refused(&header, &t.join("header-out"));
    assert!(
        err.contains("compressed segment 0") && err.contains("damaged"),
        "{err}"
    );

    // A few damaged bytes in the entropy-coded data: the frame decodes to garbage, which the
    // set's checks catch (mostly clipped; samples far below the dark frame's level).
    for (k, at) in [(1, 0x1000), (3, 0x6000)] {
        let data = t.join(format!("data{k}"));
        synth_dng(&data);
        damage(&data, |b, tiles| {
            let (start, len) = tiles[0];
            assert!(at + 8 < len);
            for i in 0..4 {
                b[start + at + 97 * i] ^= 0x5A;
            }
        });
        let err = refused(&data, &t.join(format!("data{k}-out")));
        assert!(err.contains("garbage"), "{err}");
        // At half resolution each frame is counted in the pass that bins it (no full-size
        // linear frame is kept): the same check, the same verdict.
        let err = refused_with(
            &data,
            &t.join(format!("data{k}-half")),
            &["--resolution", "half"],
        );
        assert!(err.contains("garbage"), "{err}");
    }
}

/// Damage whose garbage stays in range (no clipping, nothing below black: at 0x800 of this
/// frame's first tile the stream decodes to values offset from the truth over the rest of the
/// tile) passes every per-frame check; the Lambertian consistency check across the lights
/// refuses it, naming the frame, and nothing is written.
#[test]
fn in_range_garbage_in_one_frame_is_refused_by_the_consistency_check() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let set = t.join("set");
    synth_dng(&set);
    damage(&set, |b, tiles| {
        let (start, len) = tiles[0];
        let at = 0x800;
        assert!(at + 4 * 97 < len);
        for i in 0..4 {
            b[start + at + 97 * i] ^= 0x5A;
        }
    });
    let err = refused(&set, &t.join("out"));
    assert!(
        err.contains("disagree with the rest of the set") && !err.contains("clipped"),
        "{err}"
    );
    // Only the damaged frame is named.
    for k in (0..10).filter(|&k| k != 3) {
        assert!(!err.contains(&format!("L{k:02}.dng")), "{err}");
    }
}
