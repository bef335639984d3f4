//! Solver kernel benchmark (`cargo bench --bench solve`; not a test): the memory-read floor
//! and each least-squares kernel on the same Lambertian frames, as megapixels per second and
//! as a multiple of the floor. `PSSCAN_BENCH_MP` sets the scene size (default 4 MP);
//! `PSSCAN_BENCH_ONLY` runs only variants whose name contains it. `psscan bench` is the full
//! run-time-against-error benchmark.

use std::time::Instant;

use psscan::bench::{self, read_all, render_scene, SceneKind};
use psscan::progress::Silent;
use psscan::rig::Rig;
use psscan::solve::{self, LightSource, SolveInput};

fn main() {
    let mp: f64 = std::env::var("PSSCAN_BENCH_MP")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(4.0);
    let only = std::env::var("PSSCAN_BENCH_ONLY").unwrap_or_default();
    let rig = Rig::default_rig();
    let (_scene, frames) = render_scene(&rig, SceneKind::Lambertian, mp, &Silent).unwrap();
    let pixels = (frames.width * frames.height) as f64;
    let time = |f: &dyn Fn()| -> f64 {
        let mut t: Vec<f64> = (0..5)
            .map(|_| {
                let start = Instant::now();
                f();
                start.elapsed().as_secs_f64()
            })
            .collect();
        t.sort_by(f64::total_cmp);
        t[2]
    };
    let floor = time(&|| {
        std::hint::black_box(read_all(&frames));
    });
    println!(
        "{}x{} ({:.1} MP), {} threads",
        frames.width,
        frames.height,
        pixels / 1e6,
        rayon::current_num_threads()
    );
    println!("| kernel | s | MP/s | x floor |\n|---|---|---|---|");
    println!(
        "| memory-read floor | {floor:.4} | {:.0} | 1.00 |",
        pixels / 1e6 / floor
    );
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
        let t = time(&|| {
            std::hint::black_box(solve::solve(&input, &variant.options, &Silent).unwrap());
        });
        println!(
            "| {} | {t:.4} | {:.0} | {:.2} |",
            variant.name,
            pixels / 1e6 / t,
            t / floor
        );
    }
}
