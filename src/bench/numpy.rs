//! The NumPy peer (`benches/numpy_ps.py`): the same frames written once to a scratch folder,
//! solved by NumPy with distant lights in a child process that times itself (the file read is
//! not timed), its normals read back and compared with the ground truth.

use std::io::Write;
use std::process::Command;

use nalgebra::Vector3;
use serde_json::{json, Value};

use super::BenchOptions;
use crate::error::{Error, Result};
use crate::eval::{angle_deg, Stats};
use crate::plane::Frames;
use crate::rig::Rig;
use crate::solve::{Illumination, LightModel, LightSource, LUMINANCE_WEIGHTS};
use crate::synth::Scene;

pub struct Peer {
    pub version: String,
    solve_s: f64,
    total_s: f64,
    error: Stats,
}

impl Peer {
    /// Table rows: (name, seconds, error).
    pub fn rows(&self) -> Vec<(String, f64, Stats)> {
        vec![
            (
                "numpy pinv, 4 solves (distant)".into(),
                self.solve_s,
                self.error,
            ),
            (
                "numpy pinv, 4 solves + normalise + albedo (distant)".into(),
                self.total_s,
                self.error,
            ),
        ]
    }
}

/// Whether `python3` with NumPy is available.
pub fn available() -> bool {
    Command::new("python3")
        .args(["-c", "import numpy"])
        .output()
        .is_ok_and(|o| o.status.success())
}

pub fn run(rig: &Rig, frames: &Frames, scene: &Scene, options: &BenchOptions) -> Result<Peer> {
    let dir = &options.scratch;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let distant = Illumination::new(
        &LightSource::Rig(rig),
        LightModel::Distant,
        frames.width,
        frames.height,
        frames.window,
    )?;
    let origin = Vector3::zeros();
    let (mut directions, mut intensities) = (Vec::new(), Vec::new());
    for k in 0..distant.len() {
        let s = distant.sample(k, &origin);
        directions.push(s.direction.as_slice().to_vec());
        intensities.push(distant.rgb_scale(k).map(|c| c * s.falloff).to_vec());
    }
    let meta = json!({
        "width": frames.width, "height": frames.height, "lights": frames.lights.len(),
        "directions": directions, "intensities": intensities,
        "weights": LUMINANCE_WEIGHTS, "repeats": options.repeats.max(1),
    });
    let meta_path = dir.join("meta.json");
    std::fs::write(&meta_path, meta.to_string()).map_err(|e| Error::io(&meta_path, e))?;
    let data_path = dir.join("frames.f32");
    {
        let file = std::fs::File::create(&data_path).map_err(|e| Error::io(&data_path, e))?;
        let mut out = std::io::BufWriter::with_capacity(1 << 22, file);
        for c in 0..3 {
            for f in &frames.lights {
                let planes = f.to_planes();
                let plane = planes.channels()[c];
                for v in &plane.data {
                    out.write_all(&v.to_le_bytes())
                        .map_err(|e| Error::io(&data_path, e))?;
                }
            }
        }
        out.flush().map_err(|e| Error::io(&data_path, e))?;
    }
    let output = Command::new("python3")
        .arg(&options.numpy_script)
        .arg(dir)
        .output()
        .map_err(|e| Error::io(&options.numpy_script, e))?;
    let _ = std::fs::remove_file(&data_path);
    if !output.status.success() {
        return Err(Error::Invalid(format!(
            "{} failed: {}",
            options.numpy_script.display(),
            String::from_utf8_lossy(&output.stderr).trim()
        )));
    }
    let stdout = String::from_utf8_lossy(&output.stdout);
    let report: Value = serde_json::from_str(stdout.trim())
        .map_err(|e| Error::Invalid(format!("NumPy peer printed {stdout:?}, not JSON: {e}")))?;
    let normal_path = dir.join("normal.f32");
    let bytes = std::fs::read(&normal_path).map_err(|e| Error::io(&normal_path, e))?;
    let _ = std::fs::remove_file(&normal_path);
    let n = frames.width * frames.height;
    if bytes.len() != 3 * n * 4 {
        return Err(Error::Invalid(format!(
            "{}: {} bytes, expected {}",
            normal_path.display(),
            bytes.len(),
            3 * n * 4
        )));
    }
    let at = |c: usize, i: usize| {
        let o = 4 * (c * n + i);
        f32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]) as f64
    };
    let t = &scene.truth.normal;
    let mut errors: Vec<f64> = (0..n)
        .map(|i| {
            let got = Vector3::new(at(0, i), at(1, i), at(2, i));
            let truth = Vector3::new(t[0].data[i], t[1].data[i], t[2].data[i]).cast::<f64>();
            angle_deg(&got, &truth)
        })
        .collect();
    let field = |k: &str| report.get(k).and_then(Value::as_f64).unwrap_or(f64::NAN);
    Ok(Peer {
        version: report
            .get("numpy")
            .and_then(Value::as_str)
            .unwrap_or("?")
            .into(),
        solve_s: field("solve_s"),
        total_s: field("total_s"),
        error: Stats::of(&mut errors),
    })
}
