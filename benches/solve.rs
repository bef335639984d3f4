//! Solver kernel benchmark (`cargo bench --bench solve`; not a test): the memory-read floor
//! and each least-squares kernel on the same Lambertian frames, as megapixels per second and
//! as a multiple of the floor. `PSSCAN_BENCH_MP` sets the scene size (default 4 MP);
//! `PSSCAN_BENCH_ONLY` runs only variants whose name contains it; `PSSCAN_BENCH_REPEATS` sets
//! the timed runs (default 5). Each solve is timed right after a floor measurement and its
//! ratio taken against that floor, so load from other processes shifts both alike; the table
//! gives the minimum and median of these paired ratios, and the page faults of one solve.
//! `psscan bench` is the full run-time-against-error benchmark.

use std::time::Instant;

use psscan::bench::{self, read_all, render_scene, SceneKind};
use psscan::progress::Silent;
use psscan::rig::Rig;
use psscan::solve::{self, LightSource, SolveInput};

/// Minor page faults of this process so far.
fn page_faults() -> i64 {
    // SAFETY: getrusage writes into the struct it is given.
    unsafe {
        let mut usage: libc::rusage = std::mem::zeroed();
        libc::getrusage(libc::RUSAGE_SELF, &mut usage);
        usage.ru_minflt
    }
}

/// `perf record --delay=-1 --control=fifo:PATH` support: with `PSSCAN_PERF_CTL=PATH` set,
/// only the solves are profiled (not the scene rendering or the floor).
fn perf_control(command: &str) {
    if let Ok(path) = std::env::var("PSSCAN_PERF_CTL") {
        use std::io::Write;
        let mut fifo = std::fs::OpenOptions::new().write(true).open(path).unwrap();
        writeln!(fifo, "{command}").unwrap();
    }
}

fn timed(f: &dyn Fn()) -> f64 {
    let start = Instant::now();
    f();
    start.elapsed().as_secs_f64()
}

fn min_median(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    (v[0], v[v.len() / 2])
}

fn main() {
    let env = |name: &str| std::env::var(name).ok().and_then(|s| s.parse::<f64>().ok());
    let mp = env("PSSCAN_BENCH_MP").unwrap_or(4.0);
    let repeats = env("PSSCAN_BENCH_REPEATS").map_or(5, |r| (r as usize).max(1));
    let only = std::env::var("PSSCAN_BENCH_ONLY").unwrap_or_default();
    let rig = Rig::default_rig();
    let (_scene, frames) = render_scene(&rig, SceneKind::Lambertian, mp, &Silent).unwrap();
    let pixels = (frames.width * frames.height) as f64;
    let floor = || {
        std::hint::black_box(read_all(&frames));
    };
    floor();
    println!(
        "{}x{} ({:.1} MP), {} threads, {repeats} runs each",
        frames.width,
        frames.height,
        pixels / 1e6,
        rayon::current_num_threads()
    );
    println!(
        "| kernel | s (min) | floor s (min) | x floor (min) | x floor (median) | page faults |"
    );
    println!("|---|---|---|---|---|---|");
    let input = SolveInput {
        frames: &frames,
        lights: LightSource::Rig(&rig),
        noise: bench::bench_noise(&rig),
        exposure: 1.0,
        mask: None,
    };
    for variant in bench::variants() {
        if variant.options.method == solve::Method::Svd || !variant.name.contains(&only) {
            continue;
        }
        let (mut times, mut floors, mut ratios) = (vec![], vec![], vec![]);
        let mut faults = 0;
        for _ in 0..repeats {
            let f = timed(&floor);
            let before = page_faults();
            perf_control("enable");
            let t = timed(&|| {
                std::hint::black_box(solve::solve(&input, &variant.options, &Silent).unwrap());
            });
            perf_control("disable");
            faults = page_faults() - before;
            times.push(t);
            floors.push(f);
            ratios.push(t / f);
        }
        let (t, _) = min_median(times);
        let (f, _) = min_median(floors);
        let (r_min, r_med) = min_median(ratios);
        println!(
            "| {} | {t:.4} | {f:.4} | {r_min:.2} | {r_med:.2} | {faults} |",
            variant.name
        );
    }
}
