//! Solver kernel benchmark (`cargo bench --bench solve`; not a test): the memory-read floor
//! and each least-squares kernel on the same Lambertian frames, as megapixels per second and
//! as a multiple of the floor. `PSSCAN_BENCH_MP` sets the scene size (default 4 MP);
//! `PSSCAN_BENCH_ONLY` runs only variants whose name contains it; `PSSCAN_BENCH_REPEATS` sets
//! the timed runs (default 5); `PSSCAN_BENCH_SCENE` renders another scene (`shadows`, `sheen`,
//! `shadows+sheen`) instead of the Lambertian one, where the default options' robust path
//! does most of the work (the `default` row: `psscan solve`'s options). Each solve is timed
//! right after a floor measurement and its
//! ratio taken against that floor, so load from other processes shifts both alike; the table
//! gives the minimum and median of these paired ratios, and the page faults of one solve.
//! `psscan bench` is the full run-time-against-error benchmark.

use std::cell::RefCell;
use std::time::Instant;

use psscan::bench::{self, read_all, render_scene, SceneKind};
use psscan::progress::Silent;
use psscan::rig::Rig;
use psscan::solve::{self, LightSource, SolveInput};

/// This process's minor page faults and CPU seconds (user + system, all threads) so far.
fn usage() -> (i64, f64) {
    // SAFETY: getrusage writes into the struct it is given.
    let u = unsafe {
        let mut usage: libc::rusage = std::mem::zeroed();
        libc::getrusage(libc::RUSAGE_SELF, &mut usage);
        usage
    };
    let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    (u.ru_minflt, secs(u.ru_utime) + secs(u.ru_stime))
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

/// Wall seconds, CPU seconds and page faults of `f`. On a loaded machine the CPU time is the
/// steadier figure: it leaves out the time the threads waited for a core.
fn timed(f: &dyn Fn()) -> (f64, f64, i64) {
    let (faults, cpu) = usage();
    let start = Instant::now();
    f();
    let wall = start.elapsed().as_secs_f64();
    let (faults_after, cpu_after) = usage();
    (wall, cpu_after - cpu, faults_after - faults)
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
    let scene_name = std::env::var("PSSCAN_BENCH_SCENE").unwrap_or("lambertian".into());
    let Some(scene) = SceneKind::ALL.into_iter().find(|k| k.name() == scene_name) else {
        panic!("PSSCAN_BENCH_SCENE={scene_name}: not a scene (lambertian, shadows, sheen, shadows+sheen)");
    };
    let rig = Rig::default_rig();
    let (_scene, frames) = render_scene(&rig, scene, mp, &Silent).unwrap();
    let pixels = (frames.width * frames.height) as f64;
    let floor = || {
        std::hint::black_box(read_all(&frames));
    };
    floor();
    println!(
        "{} scene, {}x{} ({:.1} MP), {} threads, {repeats} runs each",
        scene.name(),
        frames.width,
        frames.height,
        pixels / 1e6,
        rayon::current_num_threads()
    );
    println!(
        "| kernel | s (min) | floor s (min) | x floor (min) | x floor (median) \
         | CPU x floor (min) | CPU x floor (median) | page faults |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    let input = SolveInput {
        frames: &frames,
        lights: LightSource::Rig(&rig),
        noise: bench::bench_noise(&rig),
        exposure: 1.0,
        mask: None,
    };
    // `psscan solve`'s own options beside the benchmark's variants.
    let default = bench::Variant {
        name: "default".into(),
        options: solve::SolveOptions::default().with_default_kernel(),
        ..bench::variants().swap_remove(0)
    };
    for variant in std::iter::once(default).chain(bench::variants()) {
        // Every variant is timed with fresh and with reused outputs below.
        if variant.options.kernel.method() == solve::Method::Svd
            || variant.reuse_outputs
            || !variant.name.contains(&only)
        {
            continue;
        }
        for reuse in [false, true] {
            // Reused outputs: each solve writes into the previous one's planes (the first
            // run allocates them and is not counted).
            let previous = RefCell::new(None);
            if reuse {
                *previous.borrow_mut() =
                    Some(solve::solve(&input, &variant.options, &Silent).unwrap());
            }
            let (mut times, mut floors, mut ratios, mut cpu_ratios) =
                (vec![], vec![], vec![], vec![]);
            let mut faults = 0;
            for _ in 0..repeats {
                let (f, f_cpu, _) = timed(&floor);
                perf_control("enable");
                let (t, t_cpu, t_faults) = timed(&|| {
                    let old = previous.borrow_mut().take();
                    let r = solve::solve_reusing(&input, &variant.options, &Silent, old).unwrap();
                    *previous.borrow_mut() = reuse.then_some(r);
                });
                perf_control("disable");
                faults = t_faults;
                times.push(t);
                floors.push(f);
                ratios.push(t / f);
                cpu_ratios.push(t_cpu / f_cpu);
            }
            let (t, _) = min_median(times);
            let (f, _) = min_median(floors);
            let (r_min, r_med) = min_median(ratios);
            let (c_min, c_med) = min_median(cpu_ratios);
            let name = if reuse {
                format!("{} (reused outputs)", variant.name)
            } else {
                variant.name.clone()
            };
            println!(
                "| {name} | {t:.4} | {f:.4} | {r_min:.2} | {r_med:.2} | {c_min:.2} | {c_med:.2} \
                 | {faults} |"
            );
        }
    }
}
