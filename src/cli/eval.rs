//! `psscan eval`: estimators against ground truth on DiLiGenT-layout sets, over light subsets.

use std::path::PathBuf;

use clap::Args;
use psscan::eval::{self, EvalOptions};
use psscan::sets;
use psscan::solve::{Estimator, SolveOptions};

use super::print_json;
use super::progress::Bars;

#[derive(Args)]
pub struct EvalArgs {
    /// DiLiGenT-layout folders with ground truth (Normal_gt.mat).
    #[arg(required = true)]
    sets: Vec<PathBuf>,
    /// Light counts, comma-separated (a deterministic farthest-point subset of each set's
    /// lights); "all" or a count at or above the set's is every light.
    #[arg(long, value_delimiter = ',', default_value = "all")]
    lights: Vec<String>,
    /// Estimators, comma-separated.
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = vec![Estimator::LeastSquares, Estimator::Adaptive])]
    estimator: Vec<Estimator>,
    /// Also write eval.md, eval.json and eval.svg into this folder.
    #[arg(long)]
    out: Option<PathBuf>,
}

fn parse_lights(values: &[String]) -> anyhow::Result<Vec<Option<usize>>> {
    values
        .iter()
        .map(|v| match v.trim() {
            "all" => Ok(None),
            n => n
                .parse::<usize>()
                .map(Some)
                .map_err(|_| anyhow::anyhow!("--lights: {n:?} is neither a count nor \"all\"")),
        })
        .collect()
}

pub fn eval(args: &EvalArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    let options = EvalOptions {
        lights: parse_lights(&args.lights)?,
        estimators: args.estimator.clone(),
        solve: SolveOptions::default(),
    };
    let report = sets::evaluate_sets(&args.sets, &options, bars)?;
    if let Some(out) = &args.out {
        eval::table::write(&report, out)?;
    }
    if json {
        print_json(&report);
    } else {
        print!("{}", eval::table::markdown(&report));
    }
    Ok(())
}
