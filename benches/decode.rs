//! RAW decode benchmark (`cargo bench --bench decode`; not a test).
//!
//! 1. Decode throughput in MP/s on the same 16 MP DNG files (the default rig's full 4928 x 3264
//!    sensor, psscan's synthetic textile, 14-bit lossless-JPEG DNG as cameras write it), for
//!    psscan and for a peer decoder run in the same process tree: dcraw (`-D -4`: raw samples,
//!    the counterpart of psscan's decode; `-h -4`: half-size colour, the counterpart of 2x2
//!    binning). psscan is timed from the file's bytes to its output in memory; dcraw from
//!    process start to its 16-bit PNM written to /dev/null (its file read and PNM encode are
//!    included, its process start is a few ms).
//! 2. End to end: a 16 MP, 10-light DNG set (plus dark frame) from RAW files to written maps
//!    (`sets::solve_set`), at full and at half resolution.
//! 3. Batches: four 3 MP DNG sets solved one at a time (pixels in parallel) and two at a time.
//!
//! Prints a markdown table and writes `target/bench/decode.json`. The sets are rendered once
//! into `target/bench/sets/` and reused (delete the folder to re-render).
//! `PSSCAN_BENCH_QUICK=1` shrinks everything (a smoke run).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use psscan::capture::CaptureSet;
use psscan::progress::Silent;
use psscan::raw::{self, DevelopOptions, Resolution};
use psscan::rig::Rig;
use psscan::sets::{self, BatchOptions, SolveJob};
use psscan::synth::{self, FrameEncoding, SynthSpec};
use serde_json::{json, Value};

fn main() {
    // `cargo bench` passes `--bench`; nothing else is accepted.
    let quick = std::env::var("PSSCAN_BENCH_QUICK").is_ok();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/bench");
    let sets = root.join(if quick { "sets-quick" } else { "sets" });
    std::fs::create_dir_all(&sets).unwrap();
    let rig = Rig::default_rig();
    let (w, h) = if quick {
        (1024, 768)
    } else {
        (rig.camera.width as usize, rig.camera.height as usize)
    };
    let megapixels = (w * h) as f64 / 1e6;
    let threads = rayon::current_num_threads();
    eprintln!("psscan decode benchmark: {w}x{h} ({megapixels:.1} MP), {threads} threads");

    let big = sets.join(format!("textile-{w}x{h}"));
    let render_s = ensure_set(&rig, &big, w, h, 1);
    let files: Vec<PathBuf> = (0..rig.leds.len())
        .map(|k| big.join(format!("L{k:02}.dng")))
        .collect();
    let repeats = if quick { 2 } else { 3 };

    // 1. Decode throughput on the same files.
    let mut rows: Vec<(String, String, f64)> = Vec::new();
    let bytes: Vec<Vec<u8>> = files.iter().map(|f| std::fs::read(f).unwrap()).collect();
    let per_file = |f: &dyn Fn(usize)| -> f64 {
        median(
            (0..repeats)
                .map(|_| {
                    let t = Instant::now();
                    for i in 0..files.len() {
                        f(i);
                    }
                    t.elapsed().as_secs_f64() / files.len() as f64
                })
                .collect(),
        )
    };
    // One untimed pass, so every variant starts with the files in the page cache and the
    // thread pool awake.
    for i in 0..files.len() {
        raw::decode_raw(bytes[i].clone(), &files[i]).unwrap();
    }
    let t_decode = per_file(&|i| {
        raw::decode_raw(bytes[i].clone(), &files[i]).unwrap();
    });
    rows.push((
        "psscan".into(),
        "decode to CFA samples (rawler + active area + levels)".into(),
        t_decode,
    ));
    let t_half = per_file(&|i| {
        let decoded = raw::decode_raw(bytes[i].clone(), &files[i]).unwrap();
        decoded.mosaic.develop(Resolution::Half).unwrap();
    });
    rows.push((
        "psscan".into(),
        "decode + 2x2 binning to linear RGB".into(),
        t_half,
    ));
    let t_read = per_file(&|i| {
        std::hint::black_box(std::fs::read(&files[i]).unwrap());
    });
    rows.push(("psscan".into(), "(reading the file alone)".into(), t_read));
    // Full resolution develops the whole stack at once; per file is the stack's time / 10.
    let t_full = median(
        (0..repeats)
            .map(|_| {
                let t = Instant::now();
                let mosaics: Vec<_> = (0..files.len())
                    .map(|i| {
                        raw::decode_raw(bytes[i].clone(), &files[i])
                            .unwrap()
                            .mosaic
                            .linearize()
                            .unwrap()
                    })
                    .collect();
                // Lights on a cone around the view, as a rig's: the demosaic fits every site's
                // albedo under them, as a capture set's solve does.
                let (w, h, k) = (mosaics[0].width, mosaics[0].height, mosaics.len());
                let field = raw::ShadingField::sample(w, h, 16, |_, _| {
                    Ok((0..k)
                        .map(|j| {
                            let phi = j as f64 * std::f64::consts::TAU / k as f64;
                            [0.5 * phi.cos(), 0.5 * phi.sin(), 0.87]
                        })
                        .collect())
                })
                .unwrap();
                raw::develop_stack(mosaics, None, Some(&field), Resolution::Full).unwrap();
                t.elapsed().as_secs_f64() / files.len() as f64
            })
            .collect(),
    );
    rows.push((
        "psscan".into(),
        "decode + full-resolution stack demosaic".into(),
        t_full,
    ));

    let dcraw = Command::new("dcraw").output().is_ok();
    if dcraw {
        for (flags, what) in [
            (&["-D", "-4", "-c"][..], "raw samples, 16-bit PGM (-D -4)"),
            (
                &["-h", "-4", "-c"][..],
                "half-size colour, 16-bit PPM (-h -4)",
            ),
            (
                &["-q", "0", "-4", "-c"][..],
                "bilinear full-size colour (-q 0 -4)",
            ),
        ] {
            let t = per_file(&|i| {
                let status = Command::new("dcraw")
                    .args(flags)
                    .arg(&files[i])
                    .stdout(std::process::Stdio::null())
                    .stderr(std::process::Stdio::null())
                    .status()
                    .unwrap();
                assert!(status.success(), "dcraw {flags:?} failed");
            });
            rows.push(("dcraw".into(), what.into(), t));
        }
    } else {
        eprintln!("dcraw is not installed: no peer figures");
    }

    // The same with uncompressed DNG (16-bit containers, no LJPEG to undo).
    let plain = sets.join(format!("plain-{w}x{h}.dng"));
    if !plain.exists() {
        let decoded = raw::decode_raw(bytes[0].clone(), &files[0]).unwrap();
        let dng = raw::encode_dng(
            &decoded.mosaic,
            &decoded.meta,
            14,
            rig.sensor.channel_gain,
            raw::DngStorage::Uncompressed,
        )
        .unwrap();
        std::fs::write(&plain, dng).unwrap();
    }
    let plain_bytes = std::fs::read(&plain).unwrap();
    let t_plain = median(
        (0..repeats * 3)
            .map(|_| {
                let t = Instant::now();
                raw::decode_raw(plain_bytes.clone(), &plain).unwrap();
                t.elapsed().as_secs_f64()
            })
            .collect(),
    );
    rows.push(("psscan".into(), "decode, uncompressed DNG".into(), t_plain));
    if dcraw {
        let t = median(
            (0..repeats * 3)
                .map(|_| {
                    let t = Instant::now();
                    Command::new("dcraw")
                        .args(["-D", "-4", "-c"])
                        .arg(&plain)
                        .stdout(std::process::Stdio::null())
                        .status()
                        .unwrap();
                    t.elapsed().as_secs_f64()
                })
                .collect(),
        );
        rows.push((
            "dcraw".into(),
            "raw samples, uncompressed DNG (-D -4)".into(),
            t,
        ));
    }

    // 2. End to end, RAW files to written maps.
    let mut e2e = BTreeMap::new();
    for resolution in [Resolution::Full, Resolution::Half] {
        let out = root.join(format!("maps-{resolution:?}"));
        let job = SolveJob {
            force: true,
            develop: DevelopOptions {
                resolution,
                subtract_dark: true,
            },
            ..SolveJob::default()
        };
        let t = Instant::now();
        let report = sets::solve_set(&big, &out, &job, &Silent).unwrap();
        let seconds = t.elapsed().as_secs_f64();
        let truth = report.truth.as_ref().map(|t| t.normal_error_deg.mean);
        e2e.insert(
            format!("{resolution:?}").to_lowercase(),
            json!({
                "seconds": seconds,
                "stages_s": report.timings_s,
                "output": format!("{}x{}", report.width, report.height),
                "normal_error_deg": truth,
                "predicted_normal_error_deg": report.predicted_normal_error_deg.mean,
            }),
        );
    }

    // 3. Several sets: one at a time, or two at once.
    let (bw, bh) = if quick { (512, 384) } else { (2048, 1536) };
    let batch: Vec<PathBuf> = (0..4)
        .map(|n| {
            let dir = sets.join(format!("batch-{bw}x{bh}-{n}"));
            ensure_set(&rig, &dir, bw, bh, n as u64 + 10);
            dir
        })
        .collect();
    let mut batches = BTreeMap::new();
    for parallel_sets in [1, 2] {
        let out = root.join(format!("batch-out-{parallel_sets}"));
        let _ = std::fs::remove_dir_all(&out);
        let job = SolveJob {
            force: true,
            ..SolveJob::default()
        };
        let t = Instant::now();
        let summary = sets::solve_sets(&batch, &out, &job, BatchOptions { parallel_sets }, &Silent);
        assert_eq!(summary.failed, 0);
        batches.insert(parallel_sets, t.elapsed().as_secs_f64());
    }
    let peak_rss_mb = peak_rss_mb();

    // Report.
    println!("\n## RAW decode, {w}x{h} ({megapixels:.1} MP) DNG, 14-bit lossless JPEG, {threads} threads\n");
    println!("| decoder | work | ms per file | MP/s |");
    println!("| --- | --- | ---: | ---: |");
    for (who, what, t) in &rows {
        println!(
            "| {who} | {what} | {:.1} | {:.1} |",
            t * 1e3,
            megapixels / t
        );
    }
    println!("\n## End to end, 10 lights + dark frame, RAW files to written maps\n");
    println!("| resolution | output | total s | decode s | solve s | write s | normal error deg | predicted deg |");
    println!("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |");
    for (name, v) in &e2e {
        let stage = |k: &str| v["stages_s"][k].as_f64().unwrap_or(0.0);
        println!(
            "| {name} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.3} | {:.3} |",
            v["output"].as_str().unwrap(),
            v["seconds"].as_f64().unwrap(),
            stage("decode"),
            stage("solve"),
            stage("write"),
            v["normal_error_deg"].as_f64().unwrap_or(f64::NAN),
            v["predicted_normal_error_deg"].as_f64().unwrap()
        );
    }
    println!("\n## Four {bw}x{bh} DNG sets\n");
    println!("| sets at once | seconds |");
    println!("| ---: | ---: |");
    for (n, t) in &batches {
        println!("| {n} | {t:.2} |");
    }
    println!("\npeak resident memory {peak_rss_mb:.0} MB; rendering the 16 MP set took {render_s:.0} s (0 = reused)");

    let report: Value = json!({
        "image": {"width": w, "height": h, "megapixels": megapixels},
        "threads": threads,
        "decode": rows.iter().map(|(who, what, t)| json!({
            "decoder": who, "work": what, "seconds_per_file": t, "megapixels_per_second": megapixels / t
        })).collect::<Vec<_>>(),
        "end_to_end": e2e,
        "batch": {"sets": 4, "width": bw, "height": bh, "seconds_by_parallel_sets": batches},
        "peak_rss_mb": peak_rss_mb,
    });
    let path = root.join("decode.json");
    std::fs::write(&path, serde_json::to_string_pretty(&report).unwrap()).unwrap();
    println!("wrote {}", path.display());
}

/// Renders a noisy DNG capture set of the default textile unless one is already there;
/// returns the seconds spent rendering.
fn ensure_set(rig: &Rig, dir: &Path, w: usize, h: usize, seed: u64) -> f64 {
    if CaptureSet::open(dir, None).is_ok() && dir.join("L09.dng").is_file() {
        return 0.0;
    }
    let spec = SynthSpec {
        width: w,
        height: h,
        step: 1.0,
        noise_seed: Some(seed),
        encoding: FrameEncoding::Dng,
        ..SynthSpec::demo()
    };
    let t = Instant::now();
    synth::write_synthetic_set(rig, &spec, dir, true, &Silent).unwrap();
    t.elapsed().as_secs_f64()
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(|a, b| a.total_cmp(b));
    values[values.len() / 2]
}

fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}
