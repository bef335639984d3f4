//! Helpers the end-to-end tests of the `psscan` binary share: run it, read its `--json`
//! output, its error text, and paths as arguments. Each test crate uses some of them.
#![allow(dead_code)]

use std::path::Path;
use std::process::{Command, Output};

use serde_json::Value;

/// Runs the `psscan` binary built for these tests with `args`.
pub fn psscan(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_psscan"))
        .args(args)
        .output()
        .expect("psscan runs")
}

/// The JSON summary on stdout of a run that must have succeeded.
pub fn json(output: &Output) -> Value {
    assert!(
        output.status.success(),
        "psscan failed: {}\n{}",
        String::from_utf8_lossy(&output.stderr),
        String::from_utf8_lossy(&output.stdout)
    );
    serde_json::from_slice(&output.stdout).expect("stdout is JSON")
}

/// What the run wrote on stderr.
pub fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

/// A path as a command-line argument.
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}
