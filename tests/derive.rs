//! End-to-end tests of `psscan derive` on solves of synthetic sets: the height of the solved
//! demo scene against the textile's true relief, every output checked by a decoder or
//! validator nobody here wrote (Pillow for DDS, the Khronos glTF validator), and the refusals
//! when the solve has no scale or no maps.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

mod common;

use common::{json, psscan, s, stderr};
use psscan::io::read_exr;
use psscan::maps::derive::height::{range, rms_after_plane};
use psscan::plane::Plane;
use psscan::rig::Rig;
use psscan::synth::textile::Textile;
use psscan::synth::SynthSpec;
use serde_json::Value;

/// The demo's scene (Lambertian twill with folds, sensor noise) at every 2nd sensor pixel.
const W: usize = 384;
const H: usize = 256;
const STEP: f64 = 2.0;

struct Solved {
    _dir: tempfile::TempDir,
    maps: PathBuf,
}

fn solved() -> &'static Solved {
    static SOLVED: OnceLock<Solved> = OnceLock::new();
    SOLVED.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let set = dir.path().join("set");
        let maps = dir.path().join("maps");
        let (w, h, step) = (W.to_string(), H.to_string(), STEP.to_string());
        json(&psscan(&[
            "synth",
            "--out",
            s(&set),
            "--width",
            &w,
            "--height",
            &h,
            "--step",
            &step,
            "--json",
        ]));
        json(&psscan(&["solve", s(&set), "--out", s(&maps), "--json"]));
        Solved { _dir: dir, maps }
    })
}

/// The textile's height (mm) under each pixel centre of the synthetic set.
fn true_height() -> Plane {
    let rig = Rig::default_rig();
    let mut spec = SynthSpec::demo();
    (spec.width, spec.height, spec.step) = (W, H, STEP);
    let window = spec.window(&rig);
    let mapper = rig.camera.plane_mapper(rig.sample.z_m);
    let textile = Textile::default();
    let mut z = Plane::new(W, H, 0.0);
    for r in 0..H {
        for c in 0..W {
            let (u, v) = window.to_sensor(c as f64, r as f64);
            let p = mapper.map(u, v).expect("the sample is in view");
            z.data[r * W + c] = (textile.height_at(p.x, p.y) * 1e3) as f32;
        }
    }
    z
}

fn derive(solve_dir: &Path, out: &Path, flags: &[&str]) -> Value {
    json(&psscan(
        &[&["derive", s(solve_dir), "--out", s(out), "--json"], flags].concat(),
    ))
}

#[test]
fn height_of_the_solved_demo_scene_matches_its_true_relief() {
    let out = tempfile::tempdir().unwrap();
    let derived = out.path().join("d");
    let report = derive(&solved().maps, &derived, &["--height"]);
    assert_eq!(report["height_map"]["units"], "mm");
    let z = read_exr(&derived.join("height.exr"), &["height"])
        .unwrap()
        .remove(0);
    let truth = true_height();
    let rms = rms_after_plane(&z, &truth);
    let span = range(&truth);
    eprintln!(
        "height from solved normals: RMS {rms:.4} mm of range {span:.3} mm = {:.2} % ({} mm/px)",
        100.0 * rms / span,
        report["pixel_mm"]
    );
    assert!(rms < 0.10 * span, "RMS {rms} mm vs range {span} mm");
    // The scale is the rig's: camera height over focal length, times the step.
    let rig = Rig::default_rig();
    let want = (rig.camera.position_m[2] - rig.sample.z_m) / rig.camera.fx * STEP * 1e3;
    let got = report["pixel_mm"].as_f64().unwrap();
    assert!((got - want).abs() < 1e-9 * want, "{got} vs {want}");
}

/// A Python with numpy and Pillow: $PSSCAN_PYTHON, the repository's .venv, or python3.
fn python() -> Option<PathBuf> {
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/bin/python3");
    let candidates = [
        std::env::var_os("PSSCAN_PYTHON").map(PathBuf::from),
        Some(venv),
        Some(PathBuf::from("python3")),
    ];
    candidates.into_iter().flatten().find(|p| {
        Command::new(p)
            .args(["-c", "import numpy, PIL"])
            .output()
            .is_ok_and(|o| o.status.success())
    })
}

/// The Khronos validator's folder (`npm install gltf-validator` into target/node-tools,
/// once); `None` without node and npm. Under CI a failed install is an error.
fn gltf_validator() -> Option<PathBuf> {
    let node_ok = Command::new("node")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !node_ok {
        return None;
    }
    let tools = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/node-tools");
    if !tools.join("node_modules/gltf-validator").exists() {
        std::fs::create_dir_all(&tools).unwrap();
        let ok = Command::new("npm")
            .args(["install", "--no-audit", "--no-fund", "--prefix"])
            .arg(&tools)
            .arg("gltf-validator")
            .status()
            .is_ok_and(|s| s.success());
        if !ok {
            assert!(
                std::env::var_os("CI").is_none(),
                "CI: npm install gltf-validator failed"
            );
            return None;
        }
    }
    Some(tools.join("node_modules"))
}

fn validate_gltf(gltf: &Path) -> Option<Value> {
    let Some(modules) = gltf_validator() else {
        eprintln!("SKIPPED glTF validation: node/npm or the gltf-validator package is missing");
        return None;
    };
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/scripts/validate_gltf.js");
    let out = Command::new("node")
        .env("NODE_PATH", modules)
        .arg(script)
        .arg(gltf)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "glTF validator: {text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    Some(serde_json::from_str(&text).unwrap())
}

/// Blender's own glTF importer (File > Import > glTF 2.0, run headless by
/// `tests/scripts/open_gltf_blender.py`): what it built from `gltf`, or `None` without Blender
/// (CI installs it: there its absence fails the test).
fn open_in_blender(gltf: &Path) -> Option<Value> {
    let found = Command::new("blender")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !found {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI: blender is not installed"
        );
        return None;
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/scripts/open_gltf_blender.py");
    let out = Command::new("blender")
        .args(["--background", "--factory-startup", "--python"])
        .arg(script)
        .arg("--")
        .arg(gltf)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find_map(|l| l.strip_prefix("BLENDER_JSON "))
        .unwrap_or_else(|| panic!("Blender printed no result: {text}"));
    let result: Value = serde_json::from_str(line).unwrap();
    assert!(out.status.success(), "Blender import failed: {result}");
    Some(result)
}

/// three.js (the npm package `three`, installed beside the validator) in headless Chromium:
/// its own GLTFLoader opens `gltf` and renders it; what it made of the material, or `None`
/// without Chromium or the package.
fn open_in_three_js(gltf: &Path) -> Option<Value> {
    let modules = gltf_validator()?;
    let three = modules.join("three");
    if !three.join("build/three.module.js").exists() {
        let ok = Command::new("npm")
            .args(["install", "--no-audit", "--no-fund", "--prefix"])
            .arg(modules.parent().unwrap())
            .arg("three")
            .status()
            .is_ok_and(|s| s.success());
        if !ok {
            assert!(
                std::env::var_os("CI").is_none(),
                "CI: npm install three failed"
            );
            return None;
        }
    }
    common::chromium()?;
    let template = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/scripts/open_gltf_three.html"),
    )
    .unwrap();
    let page = gltf.with_file_name("open_in_three.html");
    let html = template
        .replace("THREE_DIR", &format!("file://{}", three.display()))
        .replace("GLTF_FILE", &gltf.file_name().unwrap().to_string_lossy());
    std::fs::write(&page, html).unwrap();
    // The page imports three.js and loads the glTF from disk. On a loaded machine (the suite
    // runs tests in parallel, Blender and other Chromium pages among them) headless Chromium
    // may dump the page before the module has run; that is Chromium's timing, not the
    // material, so such an empty result is retried twice before it counts.
    let mut dom = String::new();
    for _ in 0..3 {
        dom = common::headless_dom(
            &format!("file://{}", page.display()),
            &["--allow-file-access-from-files"],
        );
        if dom.contains("THREE-BEGIN{") {
            break;
        }
    }
    std::fs::remove_file(&page).unwrap();
    let start = dom
        .find("THREE-BEGIN{")
        .unwrap_or_else(|| panic!("three.js wrote no result in three tries; the page: {dom}"))
        + "THREE-BEGIN".len();
    let end = dom[start..].find("THREE-END").unwrap() + start;
    Some(serde_json::from_str(&dom[start..end].replace("&amp;", "&")).unwrap())
}

#[test]
fn every_output_is_written_and_independent_decoders_accept_it() {
    let out = tempfile::tempdir().unwrap();
    let derived = out.path().join("d");
    let report = derive(
        &solved().maps,
        &derived,
        &[
            "--all",
            "--tile",
            "128pxx128px",
            "--roughness",
            "toksvig",
            "--base-roughness",
            "0.4",
        ],
    );
    for step in [
        "flatten",
        "tile",
        "height",
        "mips",
        "roughness",
        "textures",
        "dds",
        "gltf",
        "total",
    ] {
        assert!(
            report["timings_s"][step].as_f64().is_some(),
            "no time for {step}: {report}"
        );
    }
    for file in [
        "normal.png",
        "normal_xy.png",
        "albedo.png",
        "height.exr",
        "height.png",
        "normal.dds",
        "albedo.dds",
        "roughness.dds",
        "material.gltf",
        "material.bin",
        "gltf_basecolor.png",
        "gltf_normal.png",
        "gltf_metallic_roughness.png",
        "derive.json",
    ] {
        assert!(derived.join(file).is_file(), "{file} missing");
    }
    assert_eq!(report["width"], 128);
    let levels = report["roughness"]["mean_per_level"].as_array().unwrap();
    assert_eq!(levels.len(), 8); // 128 .. 1
    assert!((levels[0].as_f64().unwrap() - 0.4).abs() < 1e-6 && levels[3].as_f64().unwrap() > 0.41);
    // No sheen lobe was fitted: no sheen extension.
    assert!(report.get("sheen").is_none());
    let gltf = std::fs::read_to_string(derived.join("material.gltf")).unwrap();
    assert!(!gltf.contains("KHR_materials_sheen"));

    match python() {
        Some(py) => {
            let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/scripts/check_dds.py");
            let o = Command::new(py).arg(script).arg(&derived).output().unwrap();
            let text = String::from_utf8_lossy(&o.stdout);
            eprintln!("Pillow DDS check: {text}");
            assert!(
                o.status.success(),
                "{text}{}",
                String::from_utf8_lossy(&o.stderr)
            );
        }
        None => {
            eprintln!("SKIPPED DDS check: no python3 with numpy and Pillow (see .ci/install-deps)")
        }
    }
    if let Some(v) = validate_gltf(&derived.join("material.gltf")) {
        eprintln!("glTF validator: {v}");
        assert_eq!(
            (v["errors"].as_u64(), v["warnings"].as_u64()),
            (Some(0), Some(0))
        );
    }
    match open_in_three_js(&derived.join("material.gltf")) {
        Some(three) => {
            eprintln!("three.js: {three}");
            assert_eq!(three["errors"], serde_json::json!([]), "{three}");
            for map in ["map", "normalMap", "roughnessMap"] {
                assert_eq!(three[map]["width"], 128, "{map}: {three}");
            }
            // The quad is the tile's physical size (128 px at the solve's scale), in metres.
            let mm = report["pixel_mm"].as_f64().unwrap();
            let size = three["size"].as_array().unwrap();
            assert!(
                (size[0].as_f64().unwrap() - 128.0 * mm / 1000.0).abs() < 1e-6,
                "{three}"
            );
            assert!(
                three["lit_pixels"].as_u64().unwrap() > 0,
                "three.js drew nothing"
            );
        }
        None => eprintln!("SKIPPED three.js check: no chromium or npm package three"),
    }
    if let Some(blender) = open_in_blender(&derived.join("material.gltf")) {
        eprintln!("Blender: {blender}");
        assert_eq!(
            blender["import"],
            serde_json::json!(["FINISHED"]),
            "{blender}"
        );
        assert_eq!(
            (blender["meshes"].as_u64(), blender["materials"].as_u64()),
            (Some(1), Some(1))
        );
        // The quad is the tile's physical size, in metres, lying in Blender's ground plane.
        let mm = report["pixel_mm"].as_f64().unwrap();
        let size = blender["dimensions_m"].as_array().unwrap();
        assert!(
            (size[0].as_f64().unwrap() - 128.0 * mm / 1000.0).abs() < 1e-5,
            "{blender}"
        );
        // Every texture wired into the Principled BSDF, decoded, with the colour space the
        // glTF specification gives its slot.
        let inputs = &blender["material"]["inputs"];
        for (input, colour_space) in [
            ("Base Color", "sRGB"),
            ("Normal", "Non-Color"),
            ("Roughness", "Non-Color"),
        ] {
            let image = &inputs[input]["image"];
            assert_eq!(
                image["size"],
                serde_json::json!([128, 128]),
                "{input}: {blender}"
            );
            assert_eq!(image["colorspace"], colour_space, "{input}: {blender}");
            assert_eq!(image["pixels"], 128 * 128 * 4, "{input}: {blender}");
        }
    }
}

#[test]
fn a_fitted_cloth_lobe_becomes_khr_materials_sheen() {
    let dir = tempfile::tempdir().unwrap();
    let (set, maps, derived) = (
        dir.path().join("set"),
        dir.path().join("maps"),
        dir.path().join("d"),
    );
    json(&psscan(&[
        "synth",
        "--out",
        s(&set),
        "--width",
        "96",
        "--height",
        "64",
        "--step",
        "16",
        "--sheen",
        "--json",
    ]));
    let solve = json(&psscan(&[
        "solve",
        s(&set),
        "--out",
        s(&maps),
        "--sheen-fit",
        "0.35",
        "0.4",
        "4",
        "--json",
    ]));
    assert!(
        solve["fits"]["sheen"].as_u64().unwrap() > 0,
        "{}",
        solve["fits"]
    );
    let report = derive(&maps, &derived, &["--gltf"]);
    let sheen = &report["sheen"];
    assert!((sheen["roughness"].as_f64().unwrap() - 0.4 / 2f64.sqrt()).abs() < 1e-9);
    assert_eq!(sheen["color"][0].as_f64(), Some(0.35));
    if let Some(v) = validate_gltf(&derived.join("material.gltf")) {
        assert_eq!(
            (v["errors"].as_u64(), v["warnings"].as_u64()),
            (Some(0), Some(0))
        );
        assert!(
            v["extensions"].to_string().contains("KHR_materials_sheen"),
            "{v}"
        );
    }
    // three.js reads the extension into its physical material's sheen.
    if let Some(three) = open_in_three_js(&derived.join("material.gltf")) {
        assert_eq!(three["material"], "MeshPhysicalMaterial", "{three}");
        assert_eq!(three["sheen"], 1.0, "{three}");
        assert!((three["sheenRoughness"].as_f64().unwrap() - 0.4 / 2f64.sqrt()).abs() < 1e-6);
        assert!(
            (three["sheenColor"][0].as_f64().unwrap() - 0.35).abs() < 1e-6,
            "{three}"
        );
    }
}

#[test]
fn without_a_scale_mm_lengths_and_gltf_are_refused_and_nothing_is_left_behind() {
    let dir = tempfile::tempdir().unwrap();
    let copy = dir.path().join("maps");
    std::fs::create_dir(&copy).unwrap();
    for f in ["normal.exr", "albedo.exr", "confidence.exr"] {
        std::fs::copy(solved().maps.join(f), copy.join(f)).unwrap();
    }
    let mut report: Value =
        serde_json::from_str(&std::fs::read_to_string(solved().maps.join("report.json")).unwrap())
            .unwrap();
    report.as_object_mut().unwrap().remove("pixel_size_mm");
    std::fs::write(copy.join("report.json"), report.to_string()).unwrap();
    let out = dir.path().join("d");
    for (flags, needle) in [
        (&["--flatten", "5mm"][..], "pixel_size_mm"),
        (&["--gltf"][..], "--pixel-mm"),
    ] {
        let o = psscan(&[&["derive", s(&copy), "--out", s(&out)], flags].concat());
        assert_eq!(o.status.code(), Some(1));
        assert!(stderr(&o).contains(needle), "{}", stderr(&o));
        assert!(!out.exists(), "a refused derive left {out:?} behind");
    }
    // Heights still work, in pixel units; --pixel-mm supplies the scale.
    let r = derive(&copy, &out, &["--height"]);
    assert_eq!(r["height_map"]["units"], "px");
    let r = derive(&copy, &out, &["--gltf", "--pixel-mm", "0.1", "--force"]);
    assert_eq!(
        r["scale_source"],
        "given to derive (overrides the solve's report)"
    );
    // A folder without EXR maps is named.
    std::fs::remove_file(copy.join("normal.exr")).unwrap();
    let o = psscan(&[
        "derive",
        s(&copy),
        "--out",
        s(&dir.path().join("e")),
        "--height",
    ]);
    assert!(stderr(&o).contains("normal.exr"), "{}", stderr(&o));
}
