//! A bounded, deterministic mutation fuzzer for the RAW decode entry point
//! (`psscan::raw::decode_raw`), run in CI. (cargo-fuzz needs a nightly compiler, which this
//! project's CI does not have; this is the fallback the issue allows.)
//!
//! Seeds: small DNGs psscan writes (lossless-JPEG and uncompressed), the real Canon DNG, and
//! the real camera files with their pixel data stripped (NEF, CR2, CR3, DNG). Mutations:
//! truncation at a random length, flips of 1 to 8 random bits (most in the first 4 KiB, where
//! TIFF headers and IFDs live), runs of bytes overwritten with 0x00 or 0xFF, splices of a chunk
//! from another seed, and a chunk duplicated in place. The property: decoding returns (a
//! decoder panic must not escape, nothing may abort), an error names the file, and a success
//! is a well-formed mosaic. The run is seeded, so a failure reproduces; `PSSCAN_FUZZ_ITERS`
//! scales it up for a longer local run, and `PSSCAN_FUZZ_SAVE=path` keeps each input in `path`
//! before it is decoded (what is there after a crash is the culprit).

use std::path::Path;

use psscan::raw::{self, DngStorage, Mosaic, RawMeta};
use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;

fn seeds() -> Vec<(String, Vec<u8>)> {
    let (w, h) = (48, 32);
    let mosaic = Mosaic {
        width: w,
        height: h,
        pattern: Mosaic::parse_pattern("RGGB").unwrap(),
        black: [[600.0; 2]; 2],
        white: 15600.0,
        samples: (0..w * h)
            .map(|i| (600 + (i * 7919) % 15001) as u16)
            .collect(),
    };
    let meta = RawMeta {
        make: "psscan".into(),
        model: "fuzz".into(),
        width: w,
        height: h,
        iso: Some(100),
        shutter_s: Some(0.1),
        aperture: Some(8.0),
    };
    let mut seeds = vec![
        (
            "synthetic-lossless.dng".to_string(),
            raw::encode_dng(&mosaic, &meta, 14, [0.55, 1.0, 0.72], DngStorage::Lossless).unwrap(),
        ),
        (
            "synthetic-uncompressed.dng".to_string(),
            raw::encode_dng(
                &mosaic,
                &meta,
                14,
                [0.55, 1.0, 0.72],
                DngStorage::Uncompressed,
            )
            .unwrap(),
        ),
    ];
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/raw");
    for name in [
        "stripped-Nikon.nef",
        "stripped-CanonRaw.cr2",
        "stripped-CanonRaw.cr3",
        "stripped-DNG.dng",
        "real-canon550d-colorchart.dng",
    ] {
        seeds.push((name.to_string(), std::fs::read(shipped.join(name)).unwrap()));
    }
    seeds
}

fn mutate(rng: &mut Xoshiro256PlusPlus, data: &[u8], other: &[u8]) -> Vec<u8> {
    let mut out = data.to_vec();
    let len = out.len();
    match rng.gen_range(0..5) {
        0 => out.truncate(rng.gen_range(0..len)),
        1 => {
            for _ in 0..rng.gen_range(1..=8) {
                let region = if rng.gen_bool(0.8) {
                    len.min(4096)
                } else {
                    len
                };
                let at = rng.gen_range(0..region);
                out[at] ^= 1 << rng.gen_range(0..8);
            }
        }
        2 => {
            let at = rng.gen_range(0..len);
            let run = rng.gen_range(1..=64).min(len - at);
            let fill = if rng.gen_bool(0.5) { 0x00 } else { 0xFF };
            out[at..at + run].fill(fill);
        }
        3 => {
            let from = rng.gen_range(0..other.len());
            let run = rng.gen_range(1..=256).min(other.len() - from);
            let at = rng.gen_range(0..len);
            let end = (at + run).min(len);
            out[at..end].copy_from_slice(&other[from..from + (end - at)]);
        }
        _ => {
            let at = rng.gen_range(0..len);
            let run = rng.gen_range(1..=512).min(len - at);
            let chunk = out[at..at + run].to_vec();
            let to = rng.gen_range(0..len);
            out.splice(to..to, chunk);
        }
    }
    out
}

#[test]
fn mutated_raw_files_never_panic_and_errors_name_the_file() {
    raw::quiet_decoder_panics();
    let seeds = seeds();
    let scale: usize = std::env::var("PSSCAN_FUZZ_ITERS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(0x5eed);
    let (mut decoded, mut refused) = (0, 0);
    for (s, (name, data)) in seeds.iter().enumerate() {
        // The real 4.4 MB DNG decodes in ~50 ms when a mutation leaves it readable; the small
        // seeds take well under a millisecond.
        let iterations = scale * if data.len() > 1_000_000 { 60 } else { 600 };
        for n in 0..iterations {
            let other = &seeds[(s + 1 + n % (seeds.len() - 1)) % seeds.len()].1;
            let input = mutate(&mut rng, data, other);
            let path = format!("fuzz-{n}-{name}");
            if let Ok(save) = std::env::var("PSSCAN_FUZZ_SAVE") {
                // Keep the input about to be decoded, to reproduce a crash.
                std::fs::write(&save, &input).unwrap();
            }
            let started = std::time::Instant::now();
            let outcome = raw::decode_raw(input, Path::new(&path));
            if started.elapsed().as_secs_f64() > 2.0 {
                eprintln!("fuzz: {path} took {:.1} s", started.elapsed().as_secs_f64());
            }
            match outcome {
                Ok(frame) => {
                    let m = &frame.mosaic;
                    assert_eq!(m.samples.len(), m.width * m.height, "{path}");
                    assert!(m.width * m.height <= raw::MAX_SAMPLES, "{path}");
                    m.validate().unwrap();
                    decoded += 1;
                }
                Err(e) => {
                    let message = e.to_string();
                    assert!(message.contains(&path), "{path}: {message}");
                    refused += 1;
                }
            }
        }
    }
    eprintln!("fuzz: {decoded} mutated files decoded, {refused} refused cleanly");
    assert!(refused > 0 && decoded > 0);
}
