//! The report page in headless Chromium (Debian's `chromium`; `.ci/install-deps` installs it):
//! the page of a demo solve opens with every image decoded and no console error, its WebGL
//! relight draws and changes when the light moves, and the canvas matches psscan's own CPU
//! render of the same light; a damaged report.json and missing maps give a page that says so;
//! `--no-report-html` skips the page. The page runs its own checks at `report.html#selftest`
//! and writes them into the DOM, which `chromium --dump-dom` prints.
//!
//! Without Chromium on PATH these tests print why and pass without checking the page.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

mod common;
use common::chromium;

fn psscan(args: &[&str]) -> std::process::Output {
    let out = Command::new(env!("CARGO_BIN_EXE_psscan"))
        .args(args)
        .output()
        .expect("psscan runs");
    assert!(
        out.status.success(),
        "psscan {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn skip(test: &str) -> bool {
    if chromium().is_none() {
        eprintln!(
            "{test}: SKIPPED: no chromium on PATH (install Debian's chromium package, as \
             .ci/install-deps does)"
        );
        return true;
    }
    false
}

/// Opens `page#fragment` headless (WebGL through SwiftShader) and returns the DOM.
fn dump_dom(page: &Path, fragment: &str) -> String {
    common::headless_dom(&format!("file://{}#{fragment}", page.display()), &[])
}

/// The page's self-test results; Chromium's DOM dump can come before the test's image
/// decodes finish on a loaded machine, so a dump without results is retried.
fn selftest(page: &Path, fragment: &str) -> (Value, String) {
    for _ in 0..4 {
        let dom = dump_dom(page, fragment);
        if let Some(start) = dom.find("SELFTEST-BEGIN{") {
            let rest = &dom[start + "SELFTEST-BEGIN".len()..];
            let end = rest.find("SELFTEST-END").expect("self-test results end");
            let json = rest[..end]
                .replace("&amp;", "&")
                .replace("&lt;", "<")
                .replace("&gt;", ">");
            return (serde_json::from_str(&json).expect("self-test JSON"), dom);
        }
    }
    panic!(
        "{}: the page never wrote its self-test results",
        page.display()
    );
}

fn base64_decode(text: &str) -> Vec<u8> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    } as u32;
    let bytes: Vec<u8> = text.bytes().filter(|&c| c != b'=').collect();
    let mut out = Vec::new();
    for chunk in bytes.chunks(4) {
        let n = chunk
            .iter()
            .enumerate()
            .fold(0u32, |n, (k, &c)| n | value(c) << (18 - 6 * k));
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    out
}

fn demo(dir: &Path, extra: &[&str]) -> PathBuf {
    let out = dir.to_str().unwrap();
    let mut args = vec![
        "demo", "--out", out, "--width", "160", "--height", "120", "-q",
    ];
    args.extend_from_slice(extra);
    psscan(&args);
    dir.join("maps")
}

/// Per-channel differences between the canvas and the CPU render: (share of values more than
/// 1 DN apart, mean absolute difference in DN).
fn compare(canvas: &image::RgbImage, cpu: &image::RgbImage) -> (f64, f64) {
    assert_eq!(canvas.dimensions(), cpu.dimensions());
    let (mut far, mut sum) = (0usize, 0u64);
    for (a, b) in canvas.as_raw().iter().zip(cpu.as_raw()) {
        let d = (*a as i32 - *b as i32).unsigned_abs();
        far += (d > 1) as usize;
        sum += d as u64;
    }
    let n = cpu.as_raw().len() as f64;
    (far as f64 / n, sum as f64 / n)
}

/// The browser's composition of the loupe's JPEG bands (`check`: the page's self-test of
/// it) is each whole view: the demo's 160 x 120 pixels in four bands of 32 rows or fewer,
/// no pixel black (every pixel of the demo is solved: a band missing or misplaced leaves
/// black rows), and every band's pixels exactly where the band drawn alone puts them (the
/// same decoder both times, so nothing but a band drawn over another's rows can differ).
fn loupe_bands_compose_into_the_whole_views(check: &Value) {
    for view in ["albedo", "normal"] {
        let c = &check[view];
        assert_eq!(c["width"], 160, "{view}: {c}");
        assert_eq!(c["height"], 120, "{view}: {c}");
        assert_eq!(c["bands"], 4, "{view}: {c}");
        assert_eq!(c["black_pixels"], 0, "{view}: {c}");
        assert_eq!(c["band_max_difference"], 0, "{view}: {c}");
    }
}

#[test]
fn demo_page_decodes_draws_and_matches_the_cpu_relight() {
    if skip("demo_page_decodes_draws_and_matches_the_cpu_relight") {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let maps = demo(tmp.path(), &["--sheen"]);
    let page = maps.join("report.html");
    for (brdf, light, roughness) in [
        ("ggx", "0.35,0.2,0.9", "0.3"),
        ("cloth", "-0.6,0.3,0.5", "0.5"),
    ] {
        let (result, _) = selftest(
            &page,
            &format!("selftest&light={light}&brdf={brdf}&roughness={roughness}&exposure=1"),
        );
        assert_eq!(result["errors"], serde_json::json!([]), "{result}");
        assert_eq!(result["images_failed"], serde_json::json!([]), "{result}");
        // albedo, normal, status, fit, two scales and their legends, frames, two loupe views
        assert!(result["images"].as_u64().unwrap() >= 11, "{result}");
        assert_eq!(result["webgl"], true, "{result}");
        assert_eq!(result["gl_error"], 0, "{result}");
        loupe_bands_compose_into_the_whole_views(&result["loupe"]);
        // Every pixel of the demo is solved, so all of the canvas is shaded.
        assert_eq!(result["lit_pixels"], 160 * 120, "{result}");
        assert_eq!(result["changed_when_light_moved"], true, "{result}");

        let png = result["canvas_png"].as_str().unwrap();
        let canvas = image::load_from_memory(&base64_decode(
            png.strip_prefix("data:image/png;base64,").unwrap(),
        ))
        .unwrap()
        .into_rgb8();
        let cpu_path = tmp.path().join(format!("cpu-{brdf}.png"));
        psscan(&[
            "report",
            maps.to_str().unwrap(),
            "--render-light",
            light,
            "--render-out",
            cpu_path.to_str().unwrap(),
            "--brdf",
            brdf,
            "--roughness",
            roughness,
        ]);
        let cpu = image::open(&cpu_path).unwrap().into_rgb8();
        let (far, mean) = compare(&canvas, &cpu);
        // The comparison tells lights apart: the CPU render under the light mirrored through
        // the z axis (where the page moved it next) is far from this canvas.
        let mirrored: Vec<f32> = light.split(',').map(|v| v.parse().unwrap()).collect();
        let mirrored = format!("{},{},{}", -mirrored[0], -mirrored[1], mirrored[2]);
        let other_path = tmp.path().join(format!("cpu-{brdf}-mirrored.png"));
        psscan(&[
            "report",
            maps.to_str().unwrap(),
            "--render-light",
            &mirrored,
            "--render-out",
            other_path.to_str().unwrap(),
            "--brdf",
            brdf,
            "--roughness",
            roughness,
        ]);
        let other = image::open(&other_path).unwrap().into_rgb8();
        let (other_far, _) = compare(&canvas, &other);
        assert!(
            other_far > 0.1,
            "{brdf}: the mirrored light's render is as close ({other_far})"
        );
        eprintln!(
            "{brdf}: {:.4} % of values more than 1 DN apart, mean |diff| {mean:.4} DN",
            100.0 * far
        );
        // Same 8-bit inputs, same f32 arithmetic: the final conversion to 8 bits may round
        // differently (1 DN); more only where a GPU transcendental's last-bit difference
        // crosses a branch (the horizon or pole guards), a handful of pixels.
        assert!(
            far <= 0.001,
            "{brdf}: {far} of values differ by more than 1 DN"
        );
        assert!(mean <= 0.25, "{brdf}: mean difference {mean} DN");
    }
}

#[test]
fn a_damaged_report_and_missing_maps_give_a_page_that_says_so() {
    if skip("a_damaged_report_and_missing_maps_give_a_page_that_says_so") {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let maps = demo(tmp.path(), &[]);
    std::fs::remove_file(maps.join("albedo.png")).unwrap();
    std::fs::remove_file(maps.join("albedo.exr")).unwrap();
    let text = std::fs::read_to_string(maps.join("report.json")).unwrap();
    std::fs::write(maps.join("report.json"), &text[..text.len() / 2]).unwrap();
    let out = psscan(&["report", maps.to_str().unwrap(), "--json"]);
    let summary: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(
        summary["report_error"]
            .as_str()
            .unwrap()
            .contains("damaged"),
        "{summary}"
    );
    assert!(
        summary["missing"].to_string().contains("albedo.png"),
        "{summary}"
    );

    let (result, dom) = selftest(&maps.join("report.html"), "selftest");
    assert_eq!(result["errors"], serde_json::json!([]), "{result}");
    assert_eq!(result["images_failed"], serde_json::json!([]), "{result}");
    assert!(
        dom.contains("report.json: is damaged"),
        "the page does not say report.json is damaged"
    );
    assert!(
        dom.contains("albedo.png: missing"),
        "the page does not say albedo.png is missing"
    );
    // What is left is still shown: the status map from confidence.exr.
    assert!(dom.contains("id=\"img-status\""));

    // An empty folder: a page that says everything is missing, not a blank one.
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    psscan(&["report", empty.to_str().unwrap()]);
    let (result, dom) = selftest(&empty.join("report.html"), "selftest");
    assert_eq!(result["errors"], serde_json::json!([]), "{result}");
    assert!(dom.contains("report.json: cannot be read"));
    assert!(dom.contains("confidence.exr is missing"));
}

#[test]
fn no_report_html_skips_the_page() {
    let tmp = tempfile::tempdir().unwrap();
    let maps = demo(tmp.path(), &["--no-report-html"]);
    assert!(maps.join("report.json").is_file());
    assert!(!maps.join("report.html").exists());
    assert!(!maps.join("frames_preview.jpg").exists());
    assert!(
        !stage_names(&maps).contains(&"report page".to_string()),
        "no page, no page row"
    );
}

fn stage_names(maps: &Path) -> Vec<String> {
    let report: Value =
        serde_json::from_str(&std::fs::read_to_string(maps.join("report.json")).unwrap()).unwrap();
    let stages = report["stages"].as_array().expect("a stage table");
    stages
        .iter()
        .map(|s| s["stage"].as_str().unwrap().to_string())
        .collect()
}

/// Building report.html is a row of the stage table of its own (it was outside every row), and
/// the rows still add up to the total.
#[test]
fn the_page_build_has_its_own_stage_row() {
    let tmp = tempfile::tempdir().unwrap();
    let maps = demo(tmp.path(), &[]);
    let names = stage_names(&maps);
    assert!(names.contains(&"report page".to_string()), "{names:?}");
    assert_eq!(names.last().map(String::as_str), Some("other"));
    let report: Value =
        serde_json::from_str(&std::fs::read_to_string(maps.join("report.json")).unwrap()).unwrap();
    let sum: f64 = (report["stages"].as_array().unwrap().iter())
        .map(|s| s["seconds"].as_f64().unwrap())
        .sum();
    let total = report["timings_s"]["total"].as_f64().unwrap();
    assert!(
        (sum - total).abs() <= 1e-9 * total.max(1.0),
        "{sum} vs {total}"
    );
}

fn json_of(out: &std::process::Output) -> Value {
    serde_json::from_slice(&out.stdout).expect("--json prints JSON")
}

/// `solve` with derive options writes the derived maps into OUT/derived/ and the page shows
/// height and roughness; `psscan report --derived DIR` shows a separate derive's maps, says
/// so when that derive is damaged, and refuses a folder that is not a derive.
#[test]
fn derived_height_and_roughness_are_on_the_page() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    let set_s = set.to_str().unwrap();
    psscan(&[
        "synth", "--out", set_s, "--width", "160", "--height", "120", "-q",
    ]);
    let maps = tmp.path().join("maps");
    let maps_s = maps.to_str().unwrap();
    let solve = json_of(&psscan(&[
        "solve",
        set_s,
        "--out",
        maps_s,
        "--height",
        "--roughness",
        "vmf",
        "--json",
        "-q",
    ]));
    let outputs = solve["derived"]["outputs"]
        .as_object()
        .expect("derive outputs");
    assert!(maps.join("derived/derive.json").is_file());
    for name in ["height.exr", "height.png", "roughness.dds"] {
        let path = Path::new(outputs[name].as_str().unwrap());
        assert_eq!(path, maps.join("derived").join(name), "{name}");
        assert!(path.is_file(), "{}", path.display());
    }
    // No DDS was asked for: only the roughness mips' own file.
    assert!(!maps.join("derived/normal.dds").exists());
    let page = std::fs::read_to_string(maps.join("report.html")).unwrap();
    assert!(page.contains("id=\"img-height\"") && page.contains("id=\"img-roughness\""));
    assert!(!page.contains("not derived for this solve"));

    // Rebuilding the page finds the solve's own derive.
    let rebuilt = json_of(&psscan(&["report", maps_s, "--json"]));
    assert_eq!(
        rebuilt["derived_maps"],
        serde_json::json!(["height", "roughness"])
    );

    // A separate derive, named on the command line.
    let derived = tmp.path().join("d");
    let derived_s = derived.to_str().unwrap();
    psscan(&["derive", maps_s, "--out", derived_s, "--height", "-q"]);
    let named = json_of(&psscan(&[
        "report",
        maps_s,
        "--derived",
        derived_s,
        "--json",
    ]));
    assert_eq!(named["derived"].as_str(), Some(derived_s));
    assert_eq!(named["derived_maps"], serde_json::json!(["height"]));

    // A folder that is not a derive is refused, naming it.
    let refused = Command::new(env!("CARGO_BIN_EXE_psscan"))
        .args(["report", maps_s, "--derived", set_s])
        .output()
        .unwrap();
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(
        err.contains("not a derive folder") && err.contains(set_s),
        "{err}"
    );

    if !skip("derived_height_and_roughness_are_on_the_page") {
        let (result, _) = selftest(&maps.join("report.html"), "selftest");
        assert_eq!(result["errors"], serde_json::json!([]), "{result}");
        assert_eq!(result["images_failed"], serde_json::json!([]), "{result}");
    }

    // A damaged derive report: the page says so instead of showing nothing.
    std::fs::write(derived.join("derive.json"), "{ not json").unwrap();
    let damaged = json_of(&psscan(&[
        "report",
        maps_s,
        "--derived",
        derived_s,
        "--json",
    ]));
    assert_eq!(damaged["derived_maps"], serde_json::json!([]));
    let page = std::fs::read_to_string(maps.join("report.html")).unwrap();
    assert!(
        page.contains("derive.json: is damaged"),
        "the page does not say so"
    );
}
