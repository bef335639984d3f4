//! `psscan bench`: every solver variant on standard synthetic scenes, run time against mean
//! angular error, beside the memory-read floor and a NumPy peer timed in the same run.
//!
//! Scenes are the synthetic textile under the default rig over the whole sensor field, at
//! each requested size (1 MP: every 4th sensor pixel; 16 MP: the full 4928 x 3264 sensor),
//! with sensor noise, decoded to linear planes with saturation masks as a camera's RAW would
//! be. Each scene is rendered once per run.

mod floor;
mod numpy;
pub mod report;
mod scenes;

use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

use crate::error::Result;
use crate::eval::{self, angle_deg};
use crate::plane::Frames;
use crate::progress::{Progress, Silent};
use crate::rig::Rig;
use crate::solve::{
    self, Estimator, KernelChoice, LightSource, Method, PixelStatus, Precision, SolveInput,
    SolveOptions, SolveResult,
};
use crate::synth::{Scene, Sheen};

pub use floor::{input_bytes, read_all};
pub use numpy::available as numpy_available;
pub use scenes::{bench_noise, render_scene, render_window, SceneKind};

/// Above this size (megapixels) only the Lambertian scene is run, without the slow per-pixel
/// variants (SVD, robust, adaptive, exact coefficients per pixel, predicted error), and the
/// shadows + sheen scene with [`LARGE_HARD_VARIANTS`] only.
pub const LARGE_MP: f64 = 4.0;

/// What the shadows + sheen scene is solved with above [`LARGE_MP`]: the done-when
/// compares the adaptive estimator with the sheen fit against least squares there (and against
/// least squares on the Lambertian scene) at 16 MP too.
pub const LARGE_HARD_VARIANTS: [&str; 3] = [EXACT_LS, FAST_LS, FAST_ADAPTIVE_SHEEN];

/// The adaptive estimator on the streaming kernel with the material's sheen lobe.
const FAST_ADAPTIVE_SHEEN: &str = "adaptive fast f32 tiled + sheen fit";

/// Tile tolerance of the benchmark's tiled variants (degrees).
pub const TILE_TOLERANCE_DEG: f64 = 0.01;

/// What to run.
#[derive(Clone, Debug)]
pub struct BenchOptions {
    /// Scene sizes in megapixels.
    pub sizes_mp: Vec<f64>,
    /// Timed runs per variant (the median is reported); slow variants run once at 16 MP.
    pub repeats: usize,
    /// Run the NumPy peer when python3 with numpy is found.
    pub numpy: bool,
    /// Where `benches/numpy_ps.py` is.
    pub numpy_script: PathBuf,
    /// Scratch folder for the NumPy peer's input.
    pub scratch: PathBuf,
    /// Only what the speed targets need: the Lambertian scene, the floor, the
    /// [`Variant::speed`] variants, the NumPy peer and peak memory.
    pub speed_only: bool,
}

/// A solver configuration under test.
#[derive(Clone, Debug)]
pub struct Variant {
    /// The variant's name in the rows and tables; the speed targets find theirs by it
    /// ([`FAST_LS`]).
    pub name: String,
    /// The solve options that make the variant.
    pub options: SolveOptions,
    /// Also run above [`LARGE_MP`] (the slow per-pixel variants are reported at 1 MP only).
    pub large: bool,
    /// Run only on these scenes (empty: every scene).
    pub scenes: &'static [SceneKind],
    /// Timed once whatever the repeats (the sheen fit is the slowest per-pixel fit; its time
    /// per scene is in the bench table, docs/bench/bench.md).
    pub single_run: bool,
    /// Each timed solve writes into the previous solve's outputs (`solve_reusing`, as a batch
    /// of same-size captures can): no fresh output pages to fault in and zero. One untimed
    /// solve first allocates them.
    pub reuse_outputs: bool,
    /// Run by `--speed-only`.
    pub speed: bool,
}

/// The scenes the sheen-fit variants run on (on the others the sheen model has nothing to fit).
const SHEEN_SCENES: &[SceneKind] = &[SceneKind::Sheen, SceneKind::ShadowsSheen];

/// Suffix of the variants that fit the material's sheen lobe (`--sheen-fit`).
pub const SHEEN_FIT: &str = " + sheen fit";

/// The adaptive estimator on the streaming kernel: what its cost is compared with [`FAST_LS`].
pub const FAST_ADAPTIVE: &str = "adaptive fast f32 tiled";

/// The variants every scene is solved with.
pub fn variants() -> Vec<Variant> {
    let base = SolveOptions {
        predict_error: false,
        ..SolveOptions::exact(Estimator::LeastSquares)
    };
    let v = |name: &str, options: SolveOptions| Variant {
        name: name.into(),
        large: options.kernel.method() != Method::Svd
            && options.estimator() != Estimator::Robust
            && (options.kernel.tile_tolerance_deg().is_some() || !options.streaming())
            && !options.predict_error,
        reuse_outputs: false,
        speed: name.starts_with(FAST_LS),
        options,
        scenes: &[],
        single_run: false,
    };
    // The material's lobe: the renderer's own.
    let sheen = Sheen::default();
    let with_sheen = |variant: Variant| {
        let mut options = variant.options;
        options.robust.sheen = Some(sheen);
        Variant {
            name: format!("{}{SHEEN_FIT}", variant.name),
            options,
            large: false,
            scenes: SHEEN_SCENES,
            single_run: true,
            reuse_outputs: false,
            speed: false,
        }
    };
    let streaming = |precision, tiles: Option<f64>, normal_only| SolveOptions {
        kernel: KernelChoice::new(
            Estimator::LeastSquares,
            Method::NormalEquations,
            precision,
            tiles,
            true,
        )
        .expect("the bench's streaming variants are valid"),
        normal_only,
        ..base.clone()
    };
    let tiles = Some(TILE_TOLERANCE_DEG);
    // The robust estimators (exact kernel, f64), with the predicted error they rely on, and
    // the adaptive one on the streaming kernel.
    let mut estimators: Vec<Variant> = Estimator::ALL
        .into_iter()
        .filter(|&e| e != Estimator::LeastSquares)
        .map(|estimator| {
            v(
                &format!("{} f64 per-pixel (exact kernel)", estimator.name()),
                SolveOptions::exact(estimator),
            )
        })
        .collect();
    estimators.push(v(
        FAST_ADAPTIVE,
        SolveOptions {
            kernel: KernelChoice::new(
                Estimator::Adaptive,
                Method::NormalEquations,
                Precision::F32,
                tiles,
                true,
            )
            .expect("a valid streaming kernel"),
            ..streaming(Precision::F32, tiles, false)
        },
    ));
    let sheen_fits: Vec<Variant> = estimators.iter().cloned().map(with_sheen).collect();
    let mut all = vec![
        v("ls f64 per-pixel (exact kernel)", base.clone()),
        v(
            "svd f64 per-pixel",
            SolveOptions {
                kernel: KernelChoice::Exact {
                    method: Method::Svd,
                    estimator: Estimator::LeastSquares,
                },
                ..base.clone()
            },
        ),
        v(
            "ls f64 per-pixel (exact kernel, predicted error)",
            SolveOptions {
                predict_error: true,
                ..base.clone()
            },
        ),
        v(
            "ls f64 distant lights (exact kernel)",
            SolveOptions {
                light_model: solve::LightModel::Distant,
                ..base.clone()
            },
        ),
        v("fast f64 per-pixel", streaming(Precision::F64, None, false)),
        v("fast f64 tiled", streaming(Precision::F64, tiles, false)),
        v("fast f32 per-pixel", streaming(Precision::F32, None, false)),
        v(FAST_LS, streaming(Precision::F32, tiles, false)),
        Variant {
            reuse_outputs: true,
            ..v(FAST_LS_REUSED, streaming(Precision::F32, tiles, false))
        },
        v(
            "fast f32 tiled normal-only",
            streaming(Precision::F32, tiles, true),
        ),
    ];
    all.extend(estimators);
    all.extend(sheen_fits);
    all
}

/// The name of the variant the speed targets are measured on: one solve as `psscan` runs
/// it, allocating its outputs.
pub const FAST_LS: &str = "fast f32 tiled";
/// The same solve writing into a previous solve's outputs.
pub const FAST_LS_REUSED: &str = "fast f32 tiled (reused outputs)";
/// The exact least-squares kernel every variant's deviation is measured against.
pub const EXACT_LS: &str = "ls f64 per-pixel (exact kernel)";

/// One timed solve.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    /// The scene's name ([`SceneKind::name`]).
    pub scene: String,
    /// The scene's actual size in megapixels (width x height / 10^6).
    pub megapixels: f64,
    /// Scene width in pixels.
    pub width: usize,
    /// Scene height in pixels.
    pub height: usize,
    /// The solver variant's, the floor's or the NumPy peer's name.
    pub variant: String,
    /// Median wall-clock time of the timed runs, seconds.
    pub seconds: f64,
    /// Timed runs the median was taken over.
    pub runs: usize,
    /// Time over the memory-read floor of the same scene.
    pub over_floor: f64,
    /// Mean angle between the solved and the true normals over the pixels solved (degrees).
    pub mean_error_deg: f64,
    /// 95th percentile of the same angles (degrees).
    pub p95_error_deg: f64,
    /// Largest and mean angle between this variant's normals and the exact least-squares
    /// kernel's, over pixels both solved (`None` for peers and the floor).
    pub max_dev_from_exact_deg: Option<f64>,
    /// Mean angle to the exact kernel's normals (see `max_dev_from_exact_deg`).
    pub mean_dev_from_exact_deg: Option<f64>,
    /// Pixels solved, as a fraction of all.
    pub solved_fraction: f64,
    /// Pixels the robust fit ran on, as a fraction of all (0 for least squares, the floor and
    /// the peers).
    pub escalated_fraction: f64,
}

/// Peak memory of one solve.
#[derive(Clone, Debug, Serialize)]
pub struct Memory {
    /// The variant measured (always [`FAST_LS`]).
    pub variant: String,
    /// The scene's name (the Lambertian one).
    pub scene: String,
    /// The size asked for, megapixels.
    pub megapixels: f64,
    /// Bytes of the decoded input frames the solve reads.
    pub input_bytes: usize,
    /// Heap bytes live at the solve's peak that belong to it: its input plus everything it
    /// allocated (outputs, temporaries); other live data of the benchmark is not counted.
    pub peak_bytes: usize,
    /// `peak_bytes` over `input_bytes`.
    pub ratio: f64,
}

/// Everything one benchmark run measured.
#[derive(Clone, Debug, Serialize)]
pub struct BenchResult {
    /// Rayon worker threads the solves ran on.
    pub threads: usize,
    /// The CPU's model name from `/proc/cpuinfo` ("unknown" where there is none).
    pub cpu: String,
    /// Every timed solve, scene by scene: the memory-read floor first, then the variants, then the
    /// NumPy peer's rows.
    pub rows: Vec<Row>,
    /// Peak memory of the fast solve at each size (empty in a build without the `count-alloc`
    /// feature, which installs the counting allocator).
    pub memory: Vec<Memory>,
    /// The NumPy version the peer ran with; `None`: the peer was not run or was skipped.
    pub numpy: Option<String>,
    /// Estimated interpolation error of the tile grid at each size, and the tile size chosen.
    pub tiles: Vec<(f64, usize, f64)>,
    /// Wall-clock time of the whole run, seconds.
    pub seconds: f64,
}

fn solve_once(
    rig: &Rig,
    frames: &Frames,
    options: &SolveOptions,
    previous: Option<SolveResult>,
) -> Result<(SolveResult, f64)> {
    let input = SolveInput {
        frames,
        lights: LightSource::Rig(rig),
        noise: bench_noise(rig),
        exposure: 1.0,
        mask: None,
    };
    let start = Instant::now();
    let result = solve::solve_reusing(&input, options, &Silent, previous)?;
    Ok((result, start.elapsed().as_secs_f64()))
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Angle statistics between two solves' normals over pixels both solved: (max, mean).
pub fn deviation_deg(a: &SolveResult, b: &SolveResult) -> (f64, f64) {
    let (mut max, mut sum, mut n) = (0f64, 0f64, 0usize);
    for i in 0..a.status.len() {
        if a.status[i] == PixelStatus::Solved && b.status[i] == PixelStatus::Solved {
            let e = angle_deg(&a.normal_at(i), &b.normal_at(i));
            max = max.max(e);
            sum += e;
            n += 1;
        }
    }
    (max, if n > 0 { sum / n as f64 } else { 0.0 })
}

/// Runs the benchmark; `progress` sees one step per scene.
pub fn run(options: &BenchOptions, progress: &dyn Progress) -> Result<BenchResult> {
    let total = Instant::now();
    let rig = Rig::default_rig();
    let mut rows = Vec::new();
    let mut memory = Vec::new();
    let mut tiles = Vec::new();
    let mut numpy_version = None;
    let variants = variants();
    progress.begin(
        "bench",
        (options.sizes_mp.len() * SceneKind::ALL.len()) as u64,
    );
    for &mp in &options.sizes_mp {
        // Large scenes are for the speed targets and the estimators' done-when: the
        // Lambertian scene and shadows + sheen with a few variants (rendering and solving
        // every scene with every variant at 16 MP costs many times the rest of the run).
        let kinds: &[SceneKind] = if options.speed_only {
            &[SceneKind::Lambertian]
        } else if mp > LARGE_MP {
            &[SceneKind::Lambertian, SceneKind::ShadowsSheen]
        } else {
            &SceneKind::ALL
        };
        for &kind in kinds {
            let (scene, frames) = render_scene(&rig, kind, mp, &Silent)?;
            let label = |variant: &str, seconds: f64, runs: usize| Row {
                scene: kind.name().into(),
                megapixels: (frames.width * frames.height) as f64 / 1e6,
                width: frames.width,
                height: frames.height,
                variant: variant.into(),
                seconds,
                runs,
                over_floor: 0.0,
                mean_error_deg: 0.0,
                p95_error_deg: 0.0,
                max_dev_from_exact_deg: None,
                mean_dev_from_exact_deg: None,
                solved_fraction: 0.0,
                escalated_fraction: 0.0,
            };
            let floor_s = median(
                (0..options.repeats.max(3))
                    .map(|_| {
                        let start = Instant::now();
                        std::hint::black_box(read_all(&frames));
                        start.elapsed().as_secs_f64()
                    })
                    .collect(),
            );
            let mut floor_row = label("memory-read floor", floor_s, options.repeats.max(3));
            floor_row.over_floor = 1.0;
            let mut scene_rows = vec![floor_row];
            let mut exact: Option<SolveResult> = None;
            for variant in &variants {
                let large_hard = mp > LARGE_MP && kind == SceneKind::ShadowsSheen;
                if large_hard {
                    if !LARGE_HARD_VARIANTS.contains(&variant.name.as_str()) {
                        continue;
                    }
                } else if (mp > LARGE_MP && !variant.large)
                    || (options.speed_only && !variant.speed)
                {
                    continue;
                }
                if !variant.scenes.is_empty() && !variant.scenes.contains(&kind) {
                    continue;
                }
                let slow = !variant.options.streaming()
                    || variant.options.kernel.tile_tolerance_deg().is_none();
                let runs = if variant.single_run || (slow && mp > LARGE_MP) {
                    1
                } else {
                    options.repeats
                };
                let mut times = Vec::new();
                let mut result = match variant.reuse_outputs {
                    true => Some(solve_once(&rig, &frames, &variant.options, None)?.0),
                    false => None,
                };
                for _ in 0..runs {
                    let previous = result.take().filter(|_| variant.reuse_outputs);
                    let (r, t) = solve_once(&rig, &frames, &variant.options, previous)?;
                    times.push(t);
                    result = Some(r);
                }
                let result = result.expect("at least one run");
                let mut row = label(&variant.name, median(times), runs);
                fill_errors(&mut row, &result, &scene, floor_s);
                if let Some(e) = &exact {
                    let (max, mean) = deviation_deg(&result, e);
                    row.max_dev_from_exact_deg = Some(max);
                    row.mean_dev_from_exact_deg = Some(mean);
                }
                if variant.name == EXACT_LS {
                    exact = Some(result);
                }
                scene_rows.push(row);
            }
            drop(exact);
            if kind == SceneKind::Lambertian {
                if crate::alloc::COUNTING {
                    memory.push(measure_memory(&rig, &frames, kind, mp)?);
                }
                let grid = solve::tiles::plan(
                    &solve::Illumination::new(
                        &LightSource::Rig(&rig),
                        solve::LightModel::Near,
                        frames.width,
                        frames.height,
                        frames.window,
                    )?,
                    frames.width,
                    frames.height,
                    TILE_TOLERANCE_DEG,
                );
                if let Some(g) = grid {
                    tiles.push((mp, g.tile, g.estimated_max_error_deg));
                }
                if options.numpy {
                    match numpy::run(&rig, &frames, &scene, options) {
                        Ok(peer) => {
                            numpy_version = Some(peer.version.clone());
                            for (name, seconds, error) in peer.rows() {
                                let mut row = label(&name, seconds, options.repeats);
                                row.over_floor = seconds / floor_s;
                                row.mean_error_deg = error.mean;
                                row.p95_error_deg = error.p95;
                                row.solved_fraction = 1.0;
                                scene_rows.push(row);
                            }
                        }
                        Err(e) => eprintln!("psscan bench: NumPy peer skipped: {e}"),
                    }
                }
            }
            rows.extend(scene_rows);
            progress.advance(1);
        }
    }
    progress.end();
    Ok(BenchResult {
        threads: rayon::current_num_threads(),
        cpu: cpu_name(),
        rows,
        memory,
        numpy: numpy_version,
        tiles,
        seconds: total.elapsed().as_secs_f64(),
    })
}

fn fill_errors(row: &mut Row, result: &SolveResult, scene: &Scene, floor_s: f64) {
    let cmp = eval::compare(result, &scene.truth.normal, &scene.truth.albedo);
    row.over_floor = row.seconds / floor_s;
    row.mean_error_deg = cmp.normal_error_deg.mean;
    row.p95_error_deg = cmp.normal_error_deg.p95;
    row.solved_fraction = cmp.pixels as f64 / result.status.len().max(1) as f64;
    row.escalated_fraction = result.escalated as f64 / result.status.len().max(1) as f64;
}

/// Peak heap of the fast least-squares solve against its decoded input.
fn measure_memory(rig: &Rig, frames: &Frames, kind: SceneKind, mp: f64) -> Result<Memory> {
    let options = variants()
        .into_iter()
        .find(|v| v.name == FAST_LS)
        .expect("the fast variant exists")
        .options;
    let input = input_bytes(frames);
    let before = crate::alloc::current();
    crate::alloc::reset_peak();
    let (result, _) = solve_once(rig, frames, &options, None)?;
    let peak = crate::alloc::peak();
    drop(result);
    // The solve's own peak: its input plus what it added on top of everything live before.
    let peak_bytes = input + peak.saturating_sub(before);
    Ok(Memory {
        variant: FAST_LS.into(),
        scene: kind.name().into(),
        megapixels: mp,
        input_bytes: input,
        peak_bytes,
        ratio: peak_bytes as f64 / input as f64,
    })
}

fn cpu_name() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The large shadows + sheen scene's variants are ones the bench defines (a renamed variant
    /// would otherwise silently drop out of the 16 MP figures).
    #[test]
    fn large_hard_variants_exist() {
        let names: Vec<String> = variants().into_iter().map(|v| v.name).collect();
        for name in LARGE_HARD_VARIANTS {
            assert!(names.iter().any(|n| n == name), "{name} is not a variant");
        }
        assert_eq!(FAST_ADAPTIVE_SHEEN, format!("{FAST_ADAPTIVE}{SHEEN_FIT}"));
    }
}
