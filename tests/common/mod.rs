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

/// Debian's `chromium` (or another name for it) on PATH; `.ci/install-deps` installs it.
pub fn chromium() -> Option<std::path::PathBuf> {
    let path = std::env::var_os("PATH")?;
    ["chromium", "chromium-browser", "google-chrome"]
        .iter()
        .flat_map(|name| std::env::split_paths(&path).map(move |d| d.join(name)))
        .find(|p| p.is_file())
}

/// Opens `url` in headless Chromium (WebGL through SwiftShader, a fresh profile, `extra`
/// flags) and returns the DOM after the page's scripts ran.
pub fn headless_dom(url: &str, extra: &[&str]) -> String {
    let profile = tempfile::tempdir().unwrap();
    let out = Command::new(chromium().expect("chromium on PATH"))
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu-sandbox",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--no-first-run",
            "--virtual-time-budget=30000",
        ])
        .args(extra)
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .args(["--dump-dom", url])
        .output()
        .expect("chromium runs");
    String::from_utf8_lossy(&out.stdout).into_owned()
}
