//! The house's import rules (../shared/DESIGN.md, "Modules ... in layers"), checked on the
//! source text: imports run downward only, no two modules import each other, and production
//! modules never import the simulation (`synth`, `sim`).
//!
//! The graph is read from `crate::` paths (in `use` lines and inline) and, inside a top-level
//! module, from `super::` paths; unit-test code (`#[cfg(test)] mod ... { }` blocks and the
//! `tests*.rs` files they load) is left out, since tests may render scenes with `synth`.
//!
//! Where the code still departs from the rules, the departure is listed in `KNOWN_*` below
//! with the issue that removes it: the test fails on any departure not listed (new code must
//! not add one) and on any listed one that is gone (so the list only shrinks).

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

/// Layer of each top-level module under src/ (DESIGN.md's table; tools such as `bench` and the
/// binary's `cli` sit on top). A module may import only modules of a lower or equal layer, and
/// never one that imports it back.
const LAYERS: &[(&str, u32)] = &[
    ("error", 0),
    ("fsutil", 0),
    ("plane", 0),
    ("progress", 0),
    ("timing", 0),
    ("math", 0),
    ("alloc", 0),
    ("rig", 1),
    ("io", 2),
    ("raw", 3),
    ("solve", 3),
    ("eval", 4),
    ("maps", 4),
    ("region", 4),
    ("capture", 5),
    ("calibration", 6),
    ("sets", 7),
    ("synth", 7),
    ("sim", 7),
    ("bench", 8),
    ("cli", 8),
];

/// Simulation modules: only the CLI, the bench and the simulation itself may import them.
const SIMULATION: &[&str] = &["synth", "sim"];
const MAY_IMPORT_SIMULATION: &[&str] = &["cli", "bench", "synth", "sim"];

/// Departures from the rules that the code still has (issue 15, the layering pass, removes
/// them). `(from, to)` at the top level.
const KNOWN_UPWARD: &[(&str, &str)] = &[];

/// Top-level modules that are still in an import cycle, and submodules in a cycle inside a
/// top-level module, written `top::a` (issue 15).
const KNOWN_CYCLIC: &[&str] = &[];

/// `solve`'s files in the order of its chain (DESIGN.md): each may import only files before
/// it. Shared leaves first (vector lanes, the light model, the noise model), then measurements
/// and fits, the chi-square test, the sheen lobe, the options that name them, the robust fit
/// (with its data-scaled fallback), the exact kernel, the streaming kernel (with its tiles),
/// the adaptive screen.
const SOLVE_CHAIN: &[&str] = &[
    // The output planes: imports no other file of solve.
    "result",
    "lanes",
    "lights",
    "predict",
    // The frames' cross-check before the solve: light geometry and the noise model only.
    "consistency",
    "measure",
    "chi_square",
    "sheen",
    "options",
    "departures",
    "robust",
    "kernel",
    "tiles",
    "noise_sums",
    "fast",
    "adaptive",
];

fn layer(module: &str) -> Option<u32> {
    LAYERS.iter().find(|(m, _)| *m == module).map(|(_, l)| *l)
}

/// Every `.rs` file under `dir`, sorted.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for entry in fs::read_dir(dir).expect("src is readable") {
        let path = entry.unwrap().path();
        if path.is_dir() {
            out.extend(rust_files(&path));
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
    out.sort();
    out
}

/// The source with `#[cfg(test)]`-gated module blocks removed (brace-matched).
fn without_test_modules(text: &str) -> String {
    let mut out = String::new();
    let mut rest = text;
    while let Some(at) = rest.find("#[cfg(test)]") {
        out.push_str(&rest[..at]);
        let after = &rest[at..];
        let item_end = after.find([';', '{']).unwrap_or(after.len());
        if !after[..item_end].contains("mod ") || after[item_end..].starts_with(';') {
            // A gated `mod x;` (its file is skipped by name) or a gated item other than a module.
            let skip = after[..item_end].len().min(after.len());
            out.push_str(&after[..skip]);
            rest = &after[skip..];
            continue;
        }
        let mut depth = 0usize;
        let mut end = after.len();
        for (i, c) in after[item_end..].char_indices() {
            match c {
                '{' => depth += 1,
                '}' => {
                    depth -= 1;
                    if depth == 0 {
                        end = item_end + i + 1;
                        break;
                    }
                }
                _ => {}
            }
        }
        rest = &after[end..];
    }
    out.push_str(rest);
    out
}

/// Identifiers that follow `prefix` (`crate::` or `super::`), including those inside a
/// `prefix{a, b::c}` group.
fn targets_after(text: &str, prefix: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut rest = text;
    while let Some(at) = rest.find(prefix) {
        rest = &rest[at + prefix.len()..];
        if let Some(group) = rest.strip_prefix('{') {
            let close = group.find('}').unwrap_or(group.len());
            for part in group[..close].split(',') {
                let name: String = part
                    .trim()
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                if !name.is_empty() {
                    out.insert(name);
                }
            }
        } else {
            let name: String = rest
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            if !name.is_empty() {
                out.insert(name);
            }
        }
    }
    out
}

struct Graph {
    /// Top-level module -> top-level modules it imports.
    top: BTreeMap<String, BTreeSet<String>>,
    /// `top::sub` -> `top::sub` it imports inside the same top-level module.
    inner: BTreeMap<String, BTreeSet<String>>,
}

fn import_graph() -> Graph {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut graph = Graph {
        top: BTreeMap::new(),
        inner: BTreeMap::new(),
    };
    for file in rust_files(&src) {
        let rel = file.strip_prefix(&src).unwrap();
        let parts: Vec<String> = rel
            .iter()
            .map(|p| p.to_string_lossy().trim_end_matches(".rs").to_string())
            .collect();
        if parts.last().is_some_and(|p| p.starts_with("tests")) {
            continue;
        }
        let top = match parts[0].as_str() {
            "lib" => continue,
            "main" => "cli".to_string(),
            other => other.to_string(),
        };
        let text = without_test_modules(&fs::read_to_string(&file).unwrap());
        let entry = graph.top.entry(top.clone()).or_default();
        for target in targets_after(&text, "crate::") {
            if target != top {
                entry.insert(target);
            }
        }
        // Submodule edges inside `top`: `crate::top::x` and, from `top/a.rs`, `super::x`.
        let sub = parts.get(1).filter(|s| *s != "mod").cloned();
        if let Some(sub) = sub {
            let me = format!("{top}::{sub}");
            let inner = graph.inner.entry(me.clone()).or_default();
            let mut names = targets_after(&text, &format!("crate::{top}::"));
            if parts.len() == 2 {
                names.extend(targets_after(&text, "super::"));
            }
            for name in names {
                let other = format!("{top}::{name}");
                let is_file = src.join(&top).join(format!("{name}.rs")).exists()
                    || src.join(&top).join(&name).is_dir();
                if other != me && is_file {
                    inner.insert(other);
                }
            }
        }
    }
    graph
}

/// Nodes that lie on a cycle (strongly connected components of more than one node).
fn cyclic_nodes(edges: &BTreeMap<String, BTreeSet<String>>) -> BTreeSet<String> {
    let nodes: Vec<&String> = edges.keys().collect();
    let reaches = |from: &String, to: &String| -> bool {
        let mut seen = BTreeSet::new();
        let mut stack = vec![from.clone()];
        while let Some(n) = stack.pop() {
            for next in edges.get(&n).into_iter().flatten() {
                if next == to {
                    return true;
                }
                if seen.insert(next.clone()) {
                    stack.push(next.clone());
                }
            }
        }
        false
    };
    nodes
        .iter()
        .filter(|n| reaches(n, n))
        .map(|n| (*n).clone())
        .collect()
}

#[test]
fn every_module_has_a_layer() {
    let graph = import_graph();
    let missing: Vec<&String> = graph.top.keys().filter(|m| layer(m).is_none()).collect();
    assert!(
        missing.is_empty(),
        "modules without a layer in tests/layering.rs (add them as DESIGN.md places them): {missing:?}"
    );
}

#[test]
fn imports_run_downward_and_production_never_imports_the_simulation() {
    let graph = import_graph();
    let mut departures = BTreeSet::new();
    for (from, targets) in &graph.top {
        for to in targets {
            let (Some(lf), Some(lt)) = (layer(from), layer(to)) else {
                continue;
            };
            let upward = lt > lf;
            let simulation = SIMULATION.contains(&to.as_str())
                && !MAY_IMPORT_SIMULATION.contains(&from.as_str());
            if upward || simulation {
                departures.insert((from.clone(), to.clone()));
            }
        }
    }
    let known: BTreeSet<(String, String)> = KNOWN_UPWARD
        .iter()
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect();
    let new: Vec<_> = departures.difference(&known).collect();
    let gone: Vec<_> = known.difference(&departures).collect();
    assert!(
        new.is_empty(),
        "imports against DESIGN.md's layers (from -> to): {new:?}"
    );
    assert!(
        gone.is_empty(),
        "these departures are gone: remove them from KNOWN_UPWARD: {gone:?}"
    );
}

#[test]
fn no_module_imports_one_that_imports_it_back() {
    let graph = import_graph();
    let mut cyclic = cyclic_nodes(&graph.top);
    cyclic.extend(cyclic_nodes(&graph.inner));
    let known: BTreeSet<String> = KNOWN_CYCLIC.iter().map(|s| s.to_string()).collect();
    let new: Vec<_> = cyclic.difference(&known).collect();
    let gone: Vec<_> = known.difference(&cyclic).collect();
    assert!(new.is_empty(), "modules in an import cycle: {new:?}");
    assert!(
        gone.is_empty(),
        "no longer in a cycle: remove from KNOWN_CYCLIC: {gone:?}"
    );
}

#[test]
fn the_reader_sees_through_test_blocks_and_groups() {
    let text = "use crate::{a, b::c};\nfn f() { crate::d::x(); }\n#[cfg(test)]\nmod tests {\n use crate::e; fn g() { if true { } }\n}\nuse crate::f;";
    let stripped = without_test_modules(text);
    let targets = targets_after(&stripped, "crate::");
    let expected: BTreeSet<String> = ["a", "b", "d", "f"].iter().map(|s| s.to_string()).collect();
    assert_eq!(targets, expected);
}

#[test]
fn solve_is_a_chain() {
    let graph = import_graph();
    let position = |m: &str| SOLVE_CHAIN.iter().position(|c| *c == m);
    let mut against = Vec::new();
    for (from, targets) in graph.inner.iter().filter(|(m, _)| m.starts_with("solve::")) {
        let from = from.trim_start_matches("solve::");
        let Some(at) = position(from) else {
            against.push(format!("{from} is not in SOLVE_CHAIN"));
            continue;
        };
        for to in targets {
            let to = to.trim_start_matches("solve::");
            if position(to).is_none_or(|p| p >= at) {
                against.push(format!("{from} -> {to}"));
            }
        }
    }
    assert!(
        against.is_empty(),
        "solve's files import against the chain's order: {against:?}"
    );
}

/// Issue 15: no source file over 600 lines outside tests (test files, and `#[cfg(test)]`
/// modules written inline, do not count).
#[test]
fn no_source_file_is_over_600_lines() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let long: Vec<String> = rust_files(&src)
        .into_iter()
        .filter(|p| {
            let name = p.file_name().unwrap().to_string_lossy();
            let test_file = name == "tests.rs" || name.starts_with("tests_");
            !(test_file || p.components().any(|c| c.as_os_str() == "tests"))
        })
        .filter_map(|p| {
            let text = without_test_modules(&fs::read_to_string(&p).unwrap());
            let lines = text.lines().count();
            (lines > 600).then(|| format!("{} ({lines} lines)", p.display()))
        })
        .collect();
    assert!(long.is_empty(), "split these: {long:?}");
}

/// `make test`'s feature run builds only the test binaries the Makefile lists in
/// `FEATURE_TESTS`; a test file with OpenCV or gphoto2 tests missing from that list would
/// never run anywhere.
#[test]
fn every_test_file_with_feature_tests_is_in_the_makefiles_feature_run() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let makefile = std::fs::read_to_string(root.join("Makefile")).unwrap();
    let listed: BTreeSet<String> = makefile
        .split_whitespace()
        .collect::<Vec<_>>()
        .windows(2)
        .filter(|pair| pair[0] == "--test")
        .map(|pair| pair[1].to_string())
        .collect();
    for file in std::fs::read_dir(root.join("tests")).unwrap() {
        let path = file.unwrap().path();
        // This file names the markers itself.
        if path.extension().is_none_or(|e| e != "rs") || path.ends_with("layering.rs") {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap();
        let has_feature_tests = [
            "fn opencv_",
            "fn gphoto",
            "feature = \"opencv\"",
            "feature = \"gphoto2\"",
        ]
        .iter()
        .any(|marker| text.contains(marker));
        let name = path.file_stem().unwrap().to_string_lossy().to_string();
        assert!(
            !has_feature_tests || listed.contains(&name),
            "tests/{name}.rs has OpenCV or gphoto2 tests but is not in the Makefile's FEATURE_TESTS"
        );
    }
}

/// The feature run builds no unit tests of the library, so a module compiled only with a
/// feature (`gphoto2`, `opencv`) must not hold any: they would never run.
#[test]
fn no_feature_gated_module_holds_unit_tests() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    for path in rust_files(&src) {
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().map(str::trim).collect();
        for pair in lines.windows(2) {
            let gated = pair[0].starts_with("#[cfg(feature = \"")
                && (pair[1].starts_with("pub mod ") || pair[1].starts_with("mod "));
            if !gated {
                continue;
            }
            let name = pair[1]
                .trim_start_matches("pub ")
                .trim_start_matches("mod ");
            let name = name.trim_end_matches(';').trim_end_matches(" {").trim();
            let dir = path.parent().unwrap();
            // The module's body: inline after the declaration, or its own file.
            let body = if pair[1].ends_with('{') {
                text.split(pair[1]).nth(1).unwrap_or_default().to_string()
            } else {
                [
                    dir.join(format!("{name}.rs")),
                    dir.join(name).join("mod.rs"),
                ]
                .iter()
                .find_map(|p| std::fs::read_to_string(p).ok())
                .unwrap_or_default()
            };
            assert!(
                !body.contains("#[test]"),
                "{}: the feature-gated module {name} holds unit tests, which make test never runs",
                path.display()
            );
        }
    }
}

/// The features cargo resolves for each crate, one `name version features` line per crate, as
/// `cargo tree` prints them with the given dependency kinds.
fn resolved_features(edges: &str) -> BTreeMap<String, String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let output = std::process::Command::new(cargo)
        .args(["tree", "--offline", "--prefix", "none", "-e", edges])
        .args(["-f", "{p} | {f}"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("cargo tree runs");
    assert!(
        output.status.success(),
        "cargo tree failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout)
        .expect("cargo tree prints UTF-8")
        .lines()
        .filter_map(|line| line.split_once(" | "))
        .map(|(package, features)| {
            (
                package.trim_end_matches(" (*)").to_string(),
                features.trim_end_matches(" (*)").to_string(),
            )
        })
        .collect()
}

/// `make eval` and `make demo` run `cargo run --release` after `make test`'s `cargo test
/// --release`. They share one build only when the dev-dependencies turn on no feature of a
/// crate the program also uses; otherwise every crate from that one up (rawler, image,
/// psscan) compiles a second time, minutes of CI. Cargo.toml names such crates with the
/// dev-dependencies' features.
#[test]
fn the_test_build_and_the_program_build_resolve_the_same_features() {
    let program = resolved_features("normal,build");
    let with_tests = resolved_features("normal,build,dev");
    let differing: Vec<String> = program
        .iter()
        .filter_map(|(package, features)| {
            let tested = with_tests.get(package)?;
            (tested != features).then(|| format!("{package}: [{features}] vs [{tested}] in tests"))
        })
        .collect();
    assert!(
        differing.is_empty(),
        "the dev-dependencies change these crates' features; name them in Cargo.toml's \
         [dependencies] with the test build's features:\n{}",
        differing.join("\n")
    );
}
