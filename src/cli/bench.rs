//! `psscan bench`: the arguments and the run; the work is `psscan::bench`'s.

use std::path::{Path, PathBuf};

use clap::Args;

use super::progress::Bars;
use super::{print_json, values};

#[derive(Args)]
pub(super) struct BenchArgs {
    /// Folder for bench.md, bench.json and bench.svg.
    #[arg(long, default_value = "docs/bench")]
    out: PathBuf,
    /// Scene sizes in megapixels, comma-separated (each more than 0, at most 64).
    #[arg(long, value_delimiter = ',', default_values_t = vec![1.0, 16.0],
          value_parser = values::megapixels, allow_negative_numbers = true)]
    sizes: Vec<f64>,
    /// Timed runs per variant (median reported); 1 or more.
    #[arg(long, default_value_t = 3, value_parser = values::positive_count)]
    repeats: usize,
    /// Do not run the NumPy peer even when python3 and numpy are present.
    #[arg(long)]
    no_numpy: bool,
    /// Only what the speed targets need (a fraction of the full run): the
    /// Lambertian scene, the memory-read floor, the `fast f32 tiled` variants (fresh and
    /// reused outputs, normal-only), the NumPy peer and peak memory.
    #[arg(long)]
    speed_only: bool,
}

pub(super) fn bench(args: &BenchArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/numpy_ps.py");
    let numpy = !args.no_numpy && psscan::bench::numpy_available() && script.exists();
    if !args.no_numpy && !numpy {
        eprintln!(
            "psscan bench: python3 with numpy (and {}) not found; the NumPy peer is skipped \
             (pip install numpy)",
            script.display()
        );
    }
    if !psscan::alloc::COUNTING {
        eprintln!(
            "psscan bench: peak memory is not measured: this psscan was built without the \
             count-alloc feature (cargo build --release --features count-alloc)"
        );
    }
    // The output folder is checked before the long run, and written whole at the end: it
    // is the bench's own (replaced without --force), never a folder of other files.
    psscan::fsutil::check_replaceable(&args.out, true, &[])?;
    let options = psscan::bench::BenchOptions {
        sizes_mp: args.sizes.clone(),
        repeats: args.repeats,
        numpy,
        numpy_script: script,
        scratch: std::env::temp_dir().join(format!("psscan-bench-{}", std::process::id())),
        speed_only: args.speed_only,
    };
    psscan::fsutil::register_scratch(&options.scratch);
    let result = psscan::bench::run(&options, bars);
    let _ = std::fs::remove_dir_all(&options.scratch);
    psscan::fsutil::unregister_scratch(&options.scratch);
    let result = result?;
    let stage = psscan::fsutil::StagedDir::create(&args.out, true, &[])?;
    psscan::bench::report::write(&result, stage.path())?;
    stage.commit(true, &[])?;
    if json {
        print_json(&serde_json::json!({
            "result": result,
            "targets": psscan::bench::report::targets(&result),
            "estimators": psscan::bench::report::estimator_figures(&result),
            "out": args.out,
        }));
    } else {
        print!("{}", psscan::bench::report::markdown(&result));
        println!(
            "\nwrote {}/bench.md, bench.json, bench.svg",
            args.out.display()
        );
    }
    Ok(())
}
