//! The DiLiGenT reader through the CLI without `../shared`: the test writes a small set in the
//! benchmark's layout (filenames.txt, light_directions.txt, light_intensities.txt, 16-bit RGB
//! PNG frames, mask.png and Normal_gt.mat as MATLAB v5, `height x width x 3` doubles in
//! column-major order) from a rendered Lambertian sphere, then checks `psscan solve` and
//! `psscan eval` against its known normals.

use std::path::Path;
use std::process::Command;

use nalgebra::{Matrix3, Vector3};
use serde_json::Value;

const SIZE: usize = 48;
const RADIUS: f64 = 22.0;
/// The sphere's normals in the mask lean at most this far from the view (so that every light
/// below lights every mask pixel: no attached shadows, every measurement is used).
const MAX_TILT_DEG: f64 = 50.0;
/// A white surface facing a unit-intensity light straight on reads this many DN.
const SCALE: f64 = 50000.0;
const ALBEDO: [f64; 3] = [0.7, 0.55, 0.4];

/// Twelve lights within 30 degrees of the view, with different RGB intensities.
fn lights() -> Vec<([f64; 3], [f64; 3])> {
    (0..12)
        .map(|k| {
            let elevation_off = if k % 2 == 0 { 15f64 } else { 30f64 }.to_radians();
            let phi = (k as f64 * 30.0).to_radians();
            let d = [
                elevation_off.sin() * phi.cos(),
                elevation_off.sin() * phi.sin(),
                elevation_off.cos(),
            ];
            let s = 0.8 + 0.03 * k as f64;
            (d, [s, 1.1 * s, 0.9 * s])
        })
        .collect()
}

/// The sphere's unit normal at pixel `(x, y)` (DiLiGenT frame: x right, y up, z toward the
/// camera), `None` outside the mask.
fn normal_at(x: usize, y: usize) -> Option<Vector3<f64>> {
    let c = (SIZE as f64 - 1.0) / 2.0;
    let (u, v) = ((x as f64 - c) / RADIUS, (c - y as f64) / RADIUS);
    let r2 = u * u + v * v;
    let n = Vector3::new(u, v, (1.0 - r2).max(0.0).sqrt());
    (r2 < 1.0 && n.z >= MAX_TILT_DEG.to_radians().cos()).then_some(n)
}

/// A MATLAB v5 file holding one uncompressed double array `name` of size `dims`.
fn mat_v5(name: &str, dims: [usize; 3], column_major: &[f64]) -> Vec<u8> {
    fn element(out: &mut Vec<u8>, kind: u32, payload: &[u8]) {
        out.extend_from_slice(&kind.to_le_bytes());
        out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        out.extend_from_slice(payload);
        while out.len() % 8 != 0 {
            out.push(0);
        }
    }
    const MI_INT32: u32 = 5;
    const MI_UINT32: u32 = 6;
    const MI_INT8: u32 = 1;
    const MI_DOUBLE: u32 = 9;
    const MI_MATRIX: u32 = 14;
    const MX_DOUBLE_CLASS: u32 = 6;
    let mut body = Vec::new();
    let flags: Vec<u8> = [MX_DOUBLE_CLASS, 0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    element(&mut body, MI_UINT32, &flags);
    let dims: Vec<u8> = dims
        .iter()
        .flat_map(|&d| (d as i32).to_le_bytes())
        .collect();
    element(&mut body, MI_INT32, &dims);
    element(&mut body, MI_INT8, name.as_bytes());
    let values: Vec<u8> = column_major.iter().flat_map(|v| v.to_le_bytes()).collect();
    element(&mut body, MI_DOUBLE, &values);
    let mut file = b"MATLAB 5.0 MAT-file, written by psscan's tests".to_vec();
    file.resize(116, b' ');
    file.extend_from_slice(&[0u8; 8]); // no subsystem data
    file.extend_from_slice(&0x0100u16.to_le_bytes());
    file.extend_from_slice(b"IM");
    element(&mut file, MI_MATRIX, &body);
    file
}

/// Writes the sphere set; returns its mask pixel count.
fn write_sphere_set(dir: &Path) -> usize {
    std::fs::create_dir_all(dir).unwrap();
    let lights = lights();
    let (mut names, mut directions, mut intensities) =
        (String::new(), String::new(), String::new());
    for (k, (d, e)) in lights.iter().enumerate() {
        let l = Vector3::from(*d);
        let mut img =
            image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::new(SIZE as u32, SIZE as u32);
        for (x, y, px) in img.enumerate_pixels_mut() {
            if let Some(n) = normal_at(x as usize, y as usize) {
                let shade = n.dot(&l);
                assert!(shade > 0.0, "every light lights every mask pixel");
                *px = image::Rgb(std::array::from_fn(|c| {
                    (SCALE * ALBEDO[c] * e[c] * shade).round() as u16
                }));
            }
        }
        let name = format!("{:03}.png", k + 1);
        img.save(dir.join(&name)).unwrap();
        names.push_str(&format!("{name}\n"));
        directions.push_str(&format!("{} {} {}\n", d[0], d[1], d[2]));
        intensities.push_str(&format!("{} {} {}\n", e[0], e[1], e[2]));
    }
    std::fs::write(dir.join("filenames.txt"), names).unwrap();
    std::fs::write(dir.join("light_directions.txt"), directions).unwrap();
    std::fs::write(dir.join("light_intensities.txt"), intensities).unwrap();
    let mut mask = image::GrayImage::new(SIZE as u32, SIZE as u32);
    let mut normals = vec![0.0f64; SIZE * SIZE * 3];
    let mut count = 0;
    for y in 0..SIZE {
        for x in 0..SIZE {
            if let Some(n) = normal_at(x, y) {
                mask.put_pixel(x as u32, y as u32, image::Luma([255]));
                for c in 0..3 {
                    normals[y + SIZE * (x + SIZE * c)] = n[c];
                }
                count += 1;
            }
        }
    }
    mask.save(dir.join("mask.png")).unwrap();
    let mat = mat_v5("Normal_gt", [SIZE, SIZE, 3], &normals);
    std::fs::write(dir.join("Normal_gt.mat"), mat).unwrap();
    count
}

/// The worst normal error (degrees) rounding to whole DN can cause at any mask pixel. Least
/// squares `b = (L^T L)^-1 L^T m` moves by at most `|e| / s_min(L)` for a measurement error
/// `e`, and the normal turns by at most `asin(|db| / |b|)`. Each frame's error is at most 0.5
/// DN; whether the solve fits the raw measurements (rows `l_k e_k,c`, `|b|` = albedo x SCALE)
/// or first divides each by its light's intensity (rows `l_k`, errors `0.5 / e_k,c`), the bound
/// below covers both. The solve's luminance (a weighted sum of the channels, whose intensities
/// here differ by a fixed factor per channel) is no worse than its worst channel.
fn quantisation_bound_deg() -> f64 {
    let lights = lights();
    let s_min = |scale: &dyn Fn(usize) -> f64| {
        let mut m = Matrix3::zeros();
        for (k, (d, _)) in lights.iter().enumerate() {
            let l = Vector3::from(*d) * scale(k);
            m += l * l.transpose();
        }
        m.symmetric_eigenvalues().min().sqrt()
    };
    let mut worst = 0.0f64;
    for c in 0..3 {
        let raw_rows = 0.5 * (lights.len() as f64).sqrt() / s_min(&|k| lights[k].1[c]);
        let divided: f64 = lights.iter().map(|(_, e)| (0.5 / e[c]).powi(2)).sum();
        let divided_rows = divided.sqrt() / s_min(&|_| 1.0);
        let db = raw_rows.max(divided_rows);
        worst = worst.max((db / (ALBEDO[c] * SCALE)).min(1.0).asin().to_degrees());
    }
    worst
}

fn psscan(args: &[&str]) -> Value {
    let out = Command::new(env!("CARGO_BIN_EXE_psscan"))
        .args(args)
        .output()
        .expect("psscan runs");
    assert!(
        out.status.success(),
        "psscan {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("--json prints JSON")
}

#[test]
fn a_generated_diligent_sphere_solves_and_evaluates_within_the_quantisation_bound() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("sphere");
    let mask_pixels = write_sphere_set(&set);
    let bound = quantisation_bound_deg();
    assert!(bound < 0.05, "the set is meant to be nearly exact: {bound}");

    let out = tmp.path().join("out");
    let (set_s, out_s) = (set.to_str().unwrap(), out.to_str().unwrap());
    psscan(&[
        "-q",
        "solve",
        set_s,
        "--out",
        out_s,
        "--estimator",
        "ls",
        "--json",
    ]);
    let report: Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    // A DiLiGenT set's sensor noise is unknown: no predicted error (JSON null, "n/a").
    assert!(
        report["predicted_normal_error_deg"]["mean"].is_null(),
        "{}",
        report["predicted_normal_error_deg"]
    );
    let truth = &report["normal_truth"];
    assert_eq!(truth["mask_pixels"], mask_pixels);
    assert_eq!(truth["solved"], mask_pixels);
    let max = truth["normal_error_deg"]["max"].as_f64().unwrap();
    assert!(
        max <= bound,
        "solve: worst normal error {max} deg, bound {bound}"
    );

    let eval = psscan(&["-q", "eval", set_s, "--estimator", "ls", "--json"]);
    let rows = eval["rows"].as_array().unwrap();
    let ls = rows
        .iter()
        .find(|r| r["estimator"] == "ls")
        .expect("a least-squares row");
    assert_eq!(ls["lights"], 12);
    assert_eq!(ls["mask_pixels"], mask_pixels);
    assert_eq!(ls["solved"], mask_pixels);
    let max = ls["error_deg"]["max"].as_f64().unwrap();
    assert!(
        max <= bound,
        "eval: worst normal error {max} deg, bound {bound}"
    );
}

#[test]
fn the_test_writes_a_mat_file_the_layout_expects() {
    // The header is 128 bytes, then one miMATRIX element whose size covers the rest.
    let mat = mat_v5("Normal_gt", [2, 2, 3], &[0.5; 12]);
    assert!(mat.starts_with(b"MATLAB 5.0 MAT-file"));
    assert_eq!(&mat[126..128], b"IM");
    let size = u32::from_le_bytes(mat[132..136].try_into().unwrap()) as usize;
    assert_eq!(128 + 8 + size, mat.len());
}
