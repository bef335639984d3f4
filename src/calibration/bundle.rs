//! The calibration bundle: `calibration/<rig>/<name>/` with the numbers in TOML
//! (`calibration.toml`), the calibrated rig (`rig.toml`, what captures and solves load), the
//! white sheet's per-light intensity maps in EXR (`maps/Lkk_intensity.exr`), and `bundle.toml`
//! holding the bundle's id and the sha256 of every file, which capture manifests and solve
//! reports cite.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::camera::CameraCalibration;
use super::graychart::ChartReport;
use super::lights::LightFit;
use super::table::TablePose;
use super::whitesheet::{Flatness, SheetLight};
use crate::error::{Error, Result};
use crate::fsutil::{create_dir_all, sha256_file, sha256_hex, write_atomic};
use crate::maps::write::{read_exr, write_exr};
use crate::rig::Rig;

pub const NUMBERS_FILE: &str = "calibration.toml";
pub const RIG_FILE: &str = "rig.toml";
pub const INDEX_FILE: &str = "bundle.toml";

/// Every step's result; a step not run (yet) is absent.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Calibration {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraCalibration>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub table: Option<TablePose>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gray_chart: Option<ChartReport>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sheet_reflectance: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lights: Option<LightFit>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub flatness: Option<Flatness>,
}

/// `bundle.toml`: the id and the files' checksums.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BundleIndex {
    /// `<rig>/<name>/<first 12 hex digits of the checksum>`.
    pub id: String,
    /// sha256 over the sorted `file = sha256` lines of `files`.
    pub sha256: String,
    pub files: BTreeMap<String, String>,
}

/// Writes a bundle into `dir` and returns its index.
pub fn write(
    dir: &Path,
    rig_name: &str,
    name: &str,
    calibration: &Calibration,
    rig: &Rig,
    sheet: Option<&[SheetLight]>,
) -> Result<BundleIndex> {
    create_dir_all(dir)?;
    let numbers = toml::to_string_pretty(calibration)
        .map_err(|e| Error::Invalid(format!("calibration does not serialise: {e}")))?;
    write_atomic(&dir.join(NUMBERS_FILE), numbers.as_bytes())?;
    rig.save(&dir.join(RIG_FILE))?;
    let mut files = vec![NUMBERS_FILE.to_string(), RIG_FILE.to_string()];
    if let Some(sheet) = sheet {
        create_dir_all(&dir.join("maps"))?;
        for (k, light) in sheet.iter().enumerate() {
            let file = format!("maps/L{k:02}_intensity.exr");
            let [r, g, b] = [light.map(0), light.map(1), light.map(2)];
            write_exr(&dir.join(&file), &[("R", &r), ("G", &g), ("B", &b)])?;
            files.push(file);
        }
    }
    let mut sums = BTreeMap::new();
    for f in files {
        sums.insert(f.clone(), sha256_file(&dir.join(&f))?);
    }
    let sha256 = digest(&sums);
    let index = BundleIndex {
        id: format!("{rig_name}/{name}/{}", &sha256[..12]),
        sha256,
        files: sums,
    };
    let text = toml::to_string_pretty(&index).expect("an index serialises");
    write_atomic(&dir.join(INDEX_FILE), text.as_bytes())?;
    Ok(index)
}

fn digest(sums: &BTreeMap<String, String>) -> String {
    let lines: String = sums.iter().map(|(f, s)| format!("{f} = {s}\n")).collect();
    sha256_hex(lines.as_bytes())
}

/// A bundle read back, every file checked against its checksum.
pub struct Bundle {
    pub dir: PathBuf,
    pub index: BundleIndex,
    pub calibration: Calibration,
    pub rig: Rig,
}

/// Reads and verifies the bundle in `dir`: a changed or missing file is an error naming it.
pub fn read(dir: &Path) -> Result<Bundle> {
    let index_path = dir.join(INDEX_FILE);
    let text = std::fs::read_to_string(&index_path).map_err(|e| Error::io(&index_path, e))?;
    let index: BundleIndex = toml::from_str(&text)
        .map_err(|e| Error::config(&index_path, "bundle", e.message().to_string()))?;
    for (file, expected) in &index.files {
        let got = sha256_file(&dir.join(file))?;
        if &got != expected {
            return Err(Error::config(
                dir.join(file),
                "sha256",
                format!("changed since the bundle was written (expected {expected}, found {got})"),
            ));
        }
    }
    if digest(&index.files) != index.sha256 {
        return Err(Error::config(
            &index_path,
            "sha256",
            "does not match the files listed",
        ));
    }
    let numbers_path = dir.join(NUMBERS_FILE);
    let numbers =
        std::fs::read_to_string(&numbers_path).map_err(|e| Error::io(&numbers_path, e))?;
    let calibration: Calibration = toml::from_str(&numbers)
        .map_err(|e| Error::config(&numbers_path, "calibration", e.message().to_string()))?;
    let rig = Rig::load(&dir.join(RIG_FILE))?;
    Ok(Bundle {
        dir: dir.to_path_buf(),
        index,
        calibration,
        rig,
    })
}

/// Light `k`'s intensity map from a bundle (R, G, B planes over the white sheet's blocks).
pub fn read_intensity_map(dir: &Path, k: usize) -> Result<Vec<crate::plane::Plane>> {
    read_exr(
        &dir.join(format!("maps/L{k:02}_intensity.exr")),
        &["R", "G", "B"],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bundle_round_trips_and_a_changed_file_is_named() {
        let tmp = tempfile::tempdir().unwrap();
        let rig = Rig::default_rig();
        let cal = Calibration {
            sheet_reflectance: Some(0.9),
            ..Calibration::default()
        };
        let sheet = SheetLight {
            points: vec![nalgebra::Vector3::zeros(); 4],
            rgb: vec![[0.5, 0.6, 0.7]; 4],
            pixels_per_block: 64,
            grid: (2, 2),
        };
        let sheets = vec![sheet; rig.leds.len()];
        let index = write(tmp.path(), "default", "test", &cal, &rig, Some(&sheets)).unwrap();
        assert!(
            index.id.starts_with("default/test/") && index.id.len() == "default/test/".len() + 12
        );
        assert_eq!(index.files.len(), 2 + rig.leds.len());
        let back = read(tmp.path()).unwrap();
        assert_eq!(back.index, index);
        assert_eq!(back.rig, rig);
        assert_eq!(back.calibration.sheet_reflectance, Some(0.9));
        let map = read_intensity_map(tmp.path(), 3).unwrap();
        assert!((map[2].data[0] - 0.7).abs() < 1e-6);
        // Tampering is caught and the file named.
        std::fs::write(
            tmp.path().join(RIG_FILE),
            rig.to_toml_string() + "\n# edited\n",
        )
        .unwrap();
        let err = read(tmp.path()).err().unwrap().to_string();
        assert!(err.contains("rig.toml") && err.contains("changed"), "{err}");
    }
}
