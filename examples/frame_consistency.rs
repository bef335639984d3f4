//! Prints the cross-frame consistency figures of each set named on the command line (a psscan
//! capture set or a DiLiGenT-layout folder), as the solve's check sees them: per frame, its
//! robust residual scale, its worst block and that block's ratio to the median frame.
//!
//! `cargo run --release --example frame_consistency -- SET...`

use psscan::progress::Silent;
use psscan::sets::{open, SolveJob};
use psscan::solve::consistency::{frame_consistency, MODEL_GATE, NOISE_BOUND, RATIO_BOUND};
use psscan::timing::StageClock;

fn main() -> psscan::Result<()> {
    println!(
        "bounds: ratio > {RATIO_BOUND} and scale > {NOISE_BOUND} noise deviations, in blocks \
         whose median frame is within {MODEL_GATE}"
    );
    for dir in std::env::args().skip(1) {
        let job = SolveJob::default();
        let source = open(dir.as_ref(), &job)?;
        let mut clock = StageClock::start();
        let (frames, decode) = source.load(&job.develop, &Silent, &mut clock)?;
        let noise = source.noise(&decode);
        let mask = source.mask(&frames)?;
        let start = std::time::Instant::now();
        let c = frame_consistency(
            &frames,
            &source.lights(),
            job.options.light_model,
            &noise,
            mask.as_ref(),
        )?;
        let seconds = start.elapsed().as_secs_f64();
        let names = source.frame_names();
        println!(
            "{dir}: {}x{}, {} frames, {} samples, {} blocks judged, {seconds:.3} s, refused {:?}",
            frames.width,
            frames.height,
            frames.lights.len(),
            c.samples,
            c.judged_blocks,
            c.inconsistent()
        );
        for (k, f) in c.frames.iter().enumerate() {
            let name = names.get(k).map_or("?", String::as_str);
            println!(
                "  {name:>12} scale {:8.2}  worst ratio {:5.2} (block {:?}, scale {:.2})",
                f.scale, f.worst_ratio, f.worst_block, f.worst_scale
            );
        }
        let max = c.frames.iter().map(|f| f.worst_ratio).fold(0.0, f64::max);
        println!("  max worst ratio {max:.2}");
    }
    Ok(())
}
