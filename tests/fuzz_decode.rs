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

/// The lossless-JPEG segments (offset, length) of a DNG psscan wrote: the TileOffsets and
/// TileByteCounts (or strip) entries of its first IFD, read the way the TIFF spec lays them out.
fn compressed_segments(dng: &[u8]) -> Vec<(usize, usize)> {
    let u16_at = |p: usize| u16::from_le_bytes([dng[p], dng[p + 1]]) as usize;
    let u32_at = |p: usize| u32::from_le_bytes(dng[p..p + 4].try_into().unwrap()) as usize;
    assert_eq!(&dng[..2], b"II");
    let ifd = u32_at(4);
    let (mut offsets, mut counts) = (Vec::new(), Vec::new());
    for e in 0..u16_at(ifd) {
        let entry = ifd + 2 + 12 * e;
        let (tag, typ, n) = (u16_at(entry), u16_at(entry + 2), u32_at(entry + 4));
        if ![273, 279, 324, 325].contains(&tag) {
            continue;
        }
        let size = if typ == 3 { 2 } else { 4 };
        let at = if n * size <= 4 {
            entry + 8
        } else {
            u32_at(entry + 8)
        };
        let values: Vec<usize> = (0..n)
            .map(|k| {
                if typ == 3 {
                    u16_at(at + 2 * k)
                } else {
                    u32_at(at + 4 * k)
                }
            })
            .collect();
        match tag {
            273 | 324 => offsets = values,
            279 | 325 => counts = values,
            _ => {}
        }
    }
    assert!(!offsets.is_empty() && offsets.len() == counts.len());
    offsets.into_iter().zip(counts).collect()
}

/// Damage inside one compressed segment: bytes set at random, bits flipped, or a run
/// overwritten, a quarter of the time in the stream's headers (SOF, Huffman tables, SOS).
fn mutate_stream(
    rng: &mut Xoshiro256PlusPlus,
    data: &[u8],
    segments: &[(usize, usize)],
) -> Vec<u8> {
    let mut out = data.to_vec();
    let (start, len) = segments[rng.gen_range(0..segments.len())];
    let span = if rng.gen_bool(0.25) {
        len.min(120)
    } else {
        len
    };
    for _ in 0..rng.gen_range(1..=8) {
        let at = start + rng.gen_range(0..span);
        match rng.gen_range(0..3) {
            0 => out[at] = rng.gen(),
            1 => out[at] ^= 1 << rng.gen_range(0..8),
            _ => {
                let run = rng.gen_range(1..=32).min(start + len - at);
                let fill = if rng.gen_bool(0.5) { 0x00 } else { 0xFF };
                out[at..at + run].fill(fill);
            }
        }
    }
    out
}

/// The child side of `damaged_compressed_streams_stay_within_memory_and_time_caps`: decodes
/// the file `PSSCAN_FUZZ_CHILD` names and prints the outcome. Ignored: only run as a child.
#[test]
#[ignore = "run by damaged_compressed_streams_stay_within_memory_and_time_caps in a child process"]
fn decode_child() {
    let Some(path) = std::env::var_os("PSSCAN_FUZZ_CHILD") else {
        return;
    };
    raw::quiet_decoder_panics();
    let path = std::path::PathBuf::from(path);
    match raw::read_raw(&path) {
        Ok(frame) => println!("DECODED {}x{}", frame.mosaic.width, frame.mosaic.height),
        Err(e) => println!("REFUSED {e}"),
    }
}

/// The address space each child may use: what a 320x240 frame needs is a few MB; the test
/// harness, its threads and the binary take the rest. A decoder sizing its work from a
/// damaged stream would need gigabytes (the issue measured 16.8 GB) and fails to allocate.
const CHILD_MEMORY_BYTES: u64 = 1 << 30;
/// A hang detector, not a speed limit: a frame decodes in milliseconds.
const CHILD_TIME_CAP: std::time::Duration = std::time::Duration::from_secs(60);

/// Runs `decode_child` on `path` in a child process under the memory and time caps; returns
/// its stdout, or why it failed.
fn decode_in_child(path: &Path) -> Result<String, String> {
    use std::os::unix::process::CommandExt;
    use std::process::{Command, Stdio};
    let mut command = Command::new(std::env::current_exe().unwrap());
    command
        .args([
            "--ignored",
            "--exact",
            "decode_child",
            "--nocapture",
            "--test-threads",
            "1",
        ])
        .env("PSSCAN_FUZZ_CHILD", path)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    // SAFETY: setrlimit is async-signal-safe; nothing else runs between fork and exec.
    unsafe {
        command.pre_exec(|| {
            let limit = libc::rlimit {
                rlim_cur: CHILD_MEMORY_BYTES,
                rlim_max: CHILD_MEMORY_BYTES,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &limit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let mut child = command.spawn().map_err(|e| e.to_string())?;
    let started = std::time::Instant::now();
    loop {
        if let Some(status) = child.try_wait().map_err(|e| e.to_string())? {
            let out = child.wait_with_output().map_err(|e| e.to_string())?;
            let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
            if !status.success() {
                return Err(format!(
                    "child {status}: {}",
                    String::from_utf8_lossy(&out.stderr)
                ));
            }
            return Ok(stdout);
        }
        if started.elapsed() > CHILD_TIME_CAP {
            let _ = child.kill();
            let _ = child.wait();
            return Err(format!("still decoding after {CHILD_TIME_CAP:?}"));
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
}

/// Valid DNG containers (psscan's writer, 320x240 like the synthetic set) with their
/// compressed image streams damaged: each is decoded in a child process with its address
/// space capped; every one must come back decoded or refused with the file named, within the
/// caps.
#[test]
fn damaged_compressed_streams_stay_within_memory_and_time_caps() {
    let (w, h) = (320, 240);
    let mosaic = Mosaic {
        width: w,
        height: h,
        pattern: Mosaic::parse_pattern("RGGB").unwrap(),
        black: [[600.0; 2]; 2],
        white: 15600.0,
        samples: (0..w * h)
            .map(|i| (2000 + (i % w) * 20 + (i / w) * 7 + (i * 7919) % 97) as u16)
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
    let dng = raw::encode_dng(&mosaic, &meta, 14, [0.55, 1.0, 0.72], DngStorage::Lossless).unwrap();
    let segments = compressed_segments(&dng);
    let dir = tempfile::tempdir().unwrap();
    let scale: usize = std::env::var("PSSCAN_FUZZ_ITERS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(0xda7a);
    let (mut decoded, mut refused) = (0, 0);
    let mut slowest = std::time::Duration::ZERO;
    for n in 0..60 * scale {
        let name = format!("damaged-{n}.dng");
        let path = dir.path().join(&name);
        std::fs::write(&path, mutate_stream(&mut rng, &dng, &segments)).unwrap();
        let started = std::time::Instant::now();
        let out = decode_in_child(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
        slowest = slowest.max(started.elapsed());
        // The harness writes "test decode_child ... " before the child's own output.
        let outcome = |tag: &str| out.lines().find_map(|l| l.find(tag).map(|i| &l[i..]));
        if let Some(line) = outcome("DECODED ") {
            assert_eq!(line, format!("DECODED {w}x{h}"), "{name}");
            decoded += 1;
        } else if let Some(line) = outcome("REFUSED ") {
            assert!(line.contains(&name), "{name}: {line}");
            refused += 1;
        } else {
            panic!("{name}: the child printed no outcome: {out}");
        }
    }
    eprintln!(
        "damaged streams: {decoded} decoded (to be judged by the set's checks), {refused} \
         refused; slowest child {slowest:?}, largest child peak resident set {} MiB",
        children_peak_rss_kib() / 1024
    );
    assert!(refused > 0);
}

/// The largest peak resident set (KiB) of any child this process has waited for: what the
/// worst damaged stream cost, beside the cap it ran under.
fn children_peak_rss_kib() -> i64 {
    // SAFETY: getrusage fills the zeroed struct it is given and nothing else.
    unsafe {
        let mut usage: libc::rusage = std::mem::zeroed();
        libc::getrusage(libc::RUSAGE_CHILDREN, &mut usage);
        usage.ru_maxrss
    }
}
