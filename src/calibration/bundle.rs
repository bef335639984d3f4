//! The calibration bundle: `calibration/<rig>/<name>/` with the numbers in TOML
//! (`calibration.toml`), the calibrated rig (`rig.toml`, what captures and solves load), each
//! light's intensity correction over the table (`light_gains.toml`, the gain grids of
//! [`crate::solve::LightSource::Calibrated`]), the white sheet's per-light intensity maps in
//! EXR (`maps/Lkk_intensity.exr`), and `bundle.toml` holding the bundle's id and the sha256 of
//! every file, which capture manifests and solve reports cite ([`CalibrationRef`]).
//!
//! **The checksum** (`sha256` in `bundle.toml`, the manifest and the report) is defined as:
//! for every file of the bundle except `bundle.toml` itself, the line
//! `<relative path with '/' separators> = <lower-case hex SHA-256 of the file's bytes>\n`;
//! the lines sorted by path (byte order); the SHA-256 of their concatenation, in lower-case
//! hex. The id is `<rig>/<name>/<first 12 hex digits of the checksum>`, so two bundles with
//! the same id hold the same bytes. Reading a bundle recomputes every listed file's hash and
//! the checksum; any difference is an error naming the file.

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
use crate::io::{read_exr, write_exr};
use crate::plane::Plane;
use crate::rig::Rig;
use crate::solve::GainGrid;

/// The file holding the steps' numbers ([`Calibration`] as TOML), inside the bundle folder.
pub const NUMBERS_FILE: &str = "calibration.toml";
/// The calibrated rig's file inside the bundle folder: what captures and solves load.
pub const RIG_FILE: &str = "rig.toml";
/// The bundle's index ([`BundleIndex`]): its id and every other file's SHA-256. Written last.
pub const INDEX_FILE: &str = "bundle.toml";
/// The per-LED gain grids' file; present only in bundles with a white-sheet step.
pub const GAINS_FILE: &str = "light_gains.toml";

use crate::rig::CalibrationRef;

/// `light_gains.toml`: one gain grid per LED.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct GainsFile {
    lights: Vec<GainGrid>,
}

/// Every step's result; a step not run (yet) is absent.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Calibration {
    /// The camera step's intrinsics; `None`: the camera step was not run.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraCalibration>,
    /// The camera's pose over the table (table step); `None`: not run.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub table: Option<TablePose>,
    /// Per light, white balance and linearity from the gray chart; `None`: not run.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gray_chart: Option<ChartReport>,
    /// The white sheet's diffuse reflectance the sheet step assumed; `None`: no white sheet step.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sheet_reflectance: Option<f64>,
    /// The LED positions and powers fitted to the white sheet; `None`: no white sheet step.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lights: Option<LightFit>,
    /// The wizard's final check, the white sheet re-solved with the calibration; `None`: not run
    /// (the calibrate subcommands do not run it).
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
    /// Each file of the bundle except `bundle.toml`, by relative path with '/' separators, to the
    /// lower-case hex SHA-256 of its bytes.
    pub files: BTreeMap<String, String>,
}

/// Writes a bundle into `dir` and returns its index. With the white sheet's blocks, the
/// per-light intensity maps and the gain grids against `rig`'s (fitted) lights are included.
pub fn write(
    dir: &Path,
    rig_name: &str,
    name: &str,
    calibration: &Calibration,
    rig: &Rig,
    sheet: Option<&[SheetLight]>,
) -> Result<BundleIndex> {
    let (maps, gains) = match sheet {
        Some(sheet) => (
            sheet
                .iter()
                .map(|l| [l.map(0), l.map(1), l.map(2)])
                .collect(),
            Some(super::lights::gain_grids(rig, sheet)?),
        ),
        None => (Vec::new(), None),
    };
    write_parts(
        dir,
        rig_name,
        name,
        &Parts {
            calibration,
            rig,
            maps: &maps,
            gains: gains.as_deref(),
        },
    )
}

/// What goes into a bundle.
pub struct Parts<'a> {
    /// The steps' numbers, written as `calibration.toml`.
    pub calibration: &'a Calibration,
    /// The calibrated rig.
    pub rig: &'a Rig,
    /// Per light, the white sheet's R, G, B intensity maps (may be empty).
    pub maps: &'a [[Plane; 3]],
    /// Per light, the intensity correction the solve applies.
    pub gains: Option<&'a [GainGrid]>,
}

/// Writes the files of a bundle into `dir`, then its index (last, so a bundle without an
/// index is an unfinished one), and returns the index.
pub fn write_parts(dir: &Path, rig_name: &str, name: &str, parts: &Parts) -> Result<BundleIndex> {
    if let Some(lights) = &parts.calibration.lights {
        lights.check_usable(dir)?;
    }
    create_dir_all(dir)?;
    let numbers = toml::to_string_pretty(parts.calibration)
        .map_err(|e| Error::Invalid(format!("calibration does not serialise: {e}")))?;
    write_atomic(&dir.join(NUMBERS_FILE), numbers.as_bytes())?;
    parts.rig.save(&dir.join(RIG_FILE))?;
    let mut files = vec![NUMBERS_FILE.to_string(), RIG_FILE.to_string()];
    if let Some(gains) = parts.gains {
        if gains.len() != parts.rig.leds.len() {
            return Err(Error::Invalid(format!(
                "{} gain grids for a rig with {} LEDs",
                gains.len(),
                parts.rig.leds.len()
            )));
        }
        let text = toml::to_string_pretty(&GainsFile {
            lights: gains.to_vec(),
        })
        .map_err(|e| Error::Invalid(format!("gain grids do not serialise: {e}")))?;
        write_atomic(&dir.join(GAINS_FILE), text.as_bytes())?;
        files.push(GAINS_FILE.to_string());
    }
    if !parts.maps.is_empty() {
        create_dir_all(&dir.join("maps"))?;
        for (k, [r, g, b]) in parts.maps.iter().enumerate() {
            let file = map_file(k);
            write_exr(&dir.join(&file), &[("R", r), ("G", g), ("B", b)])?;
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

fn map_file(k: usize) -> String {
    format!("maps/L{k:02}_intensity.exr")
}

/// The checksum of a set of files from their SHA-256s (module docs).
fn digest(sums: &BTreeMap<String, String>) -> String {
    let lines: String = sums.iter().map(|(f, s)| format!("{f} = {s}\n")).collect();
    sha256_hex(lines.as_bytes())
}

/// A bundle read back, every file checked against its checksum.
pub struct Bundle {
    /// The bundle's folder, as given to [`read`].
    pub dir: PathBuf,
    /// The bundle's id and checksums, as `bundle.toml` holds them (verified against the files).
    pub index: BundleIndex,
    /// The steps' numbers from `calibration.toml`; a rejected LED fit in them is refused on
    /// reading.
    pub calibration: Calibration,
    /// The calibrated rig from the bundle's `rig.toml`.
    pub rig: Rig,
    /// Per light, the intensity correction (bundles with a white-sheet step).
    pub gains: Option<Vec<GainGrid>>,
}

impl Bundle {
    /// What a manifest or report records of this bundle.
    pub fn citation(&self) -> CalibrationRef {
        CalibrationRef {
            id: self.index.id.clone(),
            sha256: self.index.sha256.clone(),
            path: self.dir.canonicalize().unwrap_or_else(|_| self.dir.clone()),
        }
    }
}

/// Reads and verifies the bundle in `dir`: a changed or missing file is an error naming it.
pub fn read(dir: &Path) -> Result<Bundle> {
    let index_path = dir.join(INDEX_FILE);
    if !index_path.is_file() {
        return Err(Error::config(
            &index_path,
            "bundle",
            "not found: not a calibration bundle (a bundle folder holds bundle.toml; \
             `psscan calibrate bundle` or the wizard writes one)",
        ));
    }
    let text = std::fs::read_to_string(&index_path).map_err(|e| Error::io(&index_path, e))?;
    let index: BundleIndex = toml::from_str(&text)
        .map_err(|e| Error::config(&index_path, "bundle", e.message().to_string()))?;
    for (file, expected) in &index.files {
        let got = sha256_file(&dir.join(file))?;
        if &got != expected {
            return Err(Error::config(
                dir.join(file),
                "sha256",
                format!(
                    "changed since the bundle was written (expected {expected}, found {got}): \
                     restore the file, or assemble a new bundle (it gets a new id)"
                ),
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
    if let Some(lights) = &calibration.lights {
        // A bundle assembled before fits were judged, or edited by hand: its lights would
        // make every solve with it wrong.
        lights.check_usable(&numbers_path)?;
    }
    let rig = Rig::load(&dir.join(RIG_FILE))?;
    let gains = if index.files.contains_key(GAINS_FILE) {
        let path = dir.join(GAINS_FILE);
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let file: GainsFile = toml::from_str(&text)
            .map_err(|e| Error::config(&path, "lights", e.message().to_string()))?;
        if file.lights.len() != rig.leds.len() {
            return Err(Error::config(
                &path,
                "lights",
                format!(
                    "{} gain grids for a rig with {} LEDs",
                    file.lights.len(),
                    rig.leds.len()
                ),
            ));
        }
        Some(file.lights)
    } else {
        None
    };
    Ok(Bundle {
        dir: dir.to_path_buf(),
        index,
        calibration,
        rig,
        gains,
    })
}

/// The checksum of the bundle in `dir` as its files are now: every file `bundle.toml` lists,
/// hashed afresh (module docs). Differs from the index's `sha256` once any of them changed.
pub fn checksum(dir: &Path) -> Result<String> {
    let index_path = dir.join(INDEX_FILE);
    let text = std::fs::read_to_string(&index_path).map_err(|e| Error::io(&index_path, e))?;
    let index: BundleIndex = toml::from_str(&text)
        .map_err(|e| Error::config(&index_path, "bundle", e.message().to_string()))?;
    let mut sums = BTreeMap::new();
    for file in index.files.keys() {
        sums.insert(file.clone(), sha256_file(&dir.join(file))?);
    }
    Ok(digest(&sums))
}

/// Light `k`'s intensity map from a bundle (R, G, B planes over the white sheet's blocks).
pub fn read_intensity_map(dir: &Path, k: usize) -> Result<Vec<crate::plane::Plane>> {
    read_exr(&dir.join(map_file(k)), &["R", "G", "B"])
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
        assert_eq!(index.files.len(), 3 + rig.leds.len());
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

    #[test]
    fn the_checksum_is_the_defined_digest_and_changes_when_any_file_changes() {
        let tmp = tempfile::tempdir().unwrap();
        let rig = Rig::default_rig();
        let sheet = SheetLight {
            points: (0..16)
                .map(|i| nalgebra::Vector3::new((i % 4) as f64 * 0.01, (i / 4) as f64 * 0.01, 0.0))
                .collect(),
            rgb: vec![[0.5, 0.6, 0.7]; 16],
            pixels_per_block: 64,
            grid: (4, 4),
        };
        let sheets = vec![sheet; rig.leds.len()];
        let cal = Calibration::default();
        let index = write(tmp.path(), "default", "sum", &cal, &rig, Some(&sheets)).unwrap();
        // Numbers, rig, gains and one map per light; the index itself is not listed.
        assert_eq!(index.files.len(), 3 + rig.leds.len());
        assert!(index.files.contains_key(GAINS_FILE) && !index.files.contains_key(INDEX_FILE));
        assert_eq!(
            read(tmp.path()).unwrap().gains.unwrap().len(),
            rig.leds.len()
        );
        // The definition, spelled out: sorted `path = sha256` lines, hashed.
        let mut names: Vec<&String> = index.files.keys().collect();
        names.sort();
        let lines: String = names
            .iter()
            .map(|f| format!("{f} = {}\n", sha256_file(&tmp.path().join(f)).unwrap()))
            .collect();
        assert_eq!(index.sha256, sha256_hex(lines.as_bytes()));
        assert_eq!(checksum(tmp.path()).unwrap(), index.sha256);
        for file in index.files.keys() {
            let path = tmp.path().join(file);
            let original = std::fs::read(&path).unwrap();
            // One byte more (the numbers file of an empty calibration is empty).
            let mut changed = original.clone();
            changed.push(b' ');
            std::fs::write(&path, &changed).unwrap();
            assert_ne!(checksum(tmp.path()).unwrap(), index.sha256, "{file}");
            let err = read(tmp.path()).err().unwrap().to_string();
            assert!(
                err.contains(file.as_str()) && err.contains("changed"),
                "{err}"
            );
            std::fs::write(&path, &original).unwrap();
            assert_eq!(checksum(tmp.path()).unwrap(), index.sha256);
        }
        // Editing the index's checksum by hand is caught too.
        let index_path = tmp.path().join(INDEX_FILE);
        let text = std::fs::read_to_string(&index_path).unwrap();
        std::fs::write(&index_path, text.replace(&index.sha256, &"0".repeat(64))).unwrap();
        assert!(read(tmp.path())
            .err()
            .unwrap()
            .to_string()
            .contains("does not match"));
    }
}
