//! `manifest.toml`: what a capture set holds and how to check it. One entry per frame with its
//! SHA-256, the rig the set was shot with, the image geometry and levels, the camera settings.

use std::path::{Component, Path};

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::plane::SensorWindow;
use crate::raw::Levels;

/// The manifest's file name inside a capture set's folder.
pub const MANIFEST_FILE: &str = "manifest.toml";
/// The `format` every capture manifest carries; anything else is not a psscan capture set.
pub const FORMAT: &str = "psscan-capture";
/// The manifest version this build writes and reads; other versions are refused with a message.
pub const VERSION: u32 = 1;

/// `image.encoding` of sets whose frames are 16-bit RGB PNG/TIFF of raw digital numbers.
pub const ENCODING_DN16: &str = "dn16";
/// `image.encoding` of sets whose frames are camera RAW files (NEF, CR2, DNG, ...): the CFA
/// samples and their levels come from each file.
pub const ENCODING_RAW: &str = "raw";
/// Every `image.encoding` this build reads.
pub const ENCODINGS: [&str; 2] = [ENCODING_DN16, ENCODING_RAW];

/// A capture set's `manifest.toml`: the rig and calibration it was shot with, the image geometry
/// and levels, the camera settings, and one entry per frame with its checksum.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// Always [`FORMAT`]; checked before anything else is parsed.
    pub format: String,
    /// The manifest's version; this build reads [`VERSION`] only.
    pub version: u32,
    /// The rig the set was shot with, a file inside the set (a copy, so the set stands alone).
    pub rig_file: String,
    /// The calibration bundle the rig came from, when there was one: its id, checksum and
    /// where it was. A solve checks the bundle it uses against this.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<crate::rig::CalibrationRef>,
    /// The frames' size, place on the sensor, levels, exposure and encoding.
    pub image: ImageInfo,
    /// The camera and exposure settings recorded for the set (fields left empty where unknown).
    pub camera: CameraSettings,
    /// Present for sets rendered by `psscan synth`: where the ground truth lies.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub synthetic: Option<SyntheticInfo>,
    /// Every frame in the set: at most one dark frame and one light frame per LED, each file listed
    /// once.
    #[serde(default)]
    pub frames: Vec<FrameEntry>,
}

/// The geometry, levels and storage of a set's frames.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageInfo {
    /// Frame width in pixels (for `raw`, the mosaic's).
    pub width: usize,
    /// Frame height in pixels (for `raw`, the mosaic's).
    pub height: usize,
    /// Where the image pixels sit on the sensor (for `raw`: where the CFA samples sit).
    pub window: SensorWindow,
    /// The digital levels of `dn16` frames. `raw` frames carry their own (per CFA site) and
    /// these are informational.
    pub levels: Levels,
    /// Exposure relative to the one the rig's LED powers were measured at.
    pub exposure: f64,
    /// How frames are stored: `dn16` = 16-bit RGB PNG/TIFF of raw digital numbers; `raw` =
    /// camera RAW files (the CFA samples; width and height are the mosaic's).
    pub encoding: String,
}

/// The camera and its exposure settings as a set records them; a RAW frame whose metadata
/// disagrees with a recorded setting is refused on loading.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct CameraSettings {
    /// The camera's name or model as it reports itself.
    pub model: String,
    /// ISO sensitivity; `None`: not known (the camera did not report it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub iso: Option<u32>,
    /// Shutter time in seconds; `None`: not known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shutter_s: Option<f64>,
    /// Aperture as an f-number (8.0 for f/8); `None`: not known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub aperture: Option<f64>,
}

impl CameraSettings {
    /// Whether frames taken with `other` expose like frames taken with these settings: the
    /// ISO, shutter time and aperture agree wherever both are known (times and f-numbers
    /// within 1 %, the rounding of the values cameras report).
    pub fn same_exposure(&self, other: &CameraSettings) -> bool {
        let close = |a: f64, b: f64| (a / b - 1.0).abs() <= 0.01;
        let agree = |a: Option<f64>, b: Option<f64>, same: &dyn Fn(f64, f64) -> bool| match (a, b) {
            (Some(a), Some(b)) => same(a, b),
            _ => true,
        };
        agree(
            self.iso.map(f64::from),
            other.iso.map(f64::from),
            &|a, b| a == b,
        ) && agree(self.shutter_s, other.shutter_s, &close)
            && agree(self.aperture, other.aperture, &close)
    }

    /// The exposure in words, e.g. `ISO 100, 1/60 s, f/8` (`exposure not reported` when
    /// the camera gave none of it).
    pub fn exposure_text(&self) -> String {
        let mut parts = Vec::new();
        if let Some(iso) = self.iso {
            parts.push(format!("ISO {iso}"));
        }
        if let Some(t) = self.shutter_s {
            parts.push(if t < 1.0 {
                format!("1/{} s", (1.0 / t).round())
            } else {
                format!("{t} s")
            });
        }
        if let Some(f) = self.aperture {
            parts.push(format!("f/{f}"));
        }
        if parts.is_empty() {
            "exposure not reported".into()
        } else {
            parts.join(", ")
        }
    }
}

/// Where a synthetic set's ground truth and render specification lie, both inside the set.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyntheticInfo {
    /// Folder (inside the set) with `normal.exr` and `albedo.exr`.
    pub truth_dir: String,
    /// The full render specification, so the set can be re-rendered.
    pub spec_file: String,
}

/// Whether a frame was shot with all LEDs off or with one on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameKind {
    /// All LEDs off.
    Dark,
    /// One LED on.
    Light,
}

/// One frame of a capture set as the manifest lists it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameEntry {
    /// Dark frame or light frame.
    pub kind: FrameKind,
    /// LED index for `light` frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub light: Option<usize>,
    /// File name relative to the set's folder.
    pub file: String,
    /// Lower-case hex SHA-256 of the file's bytes, checked when the set is read.
    pub sha256: String,
}

impl Manifest {
    /// Parses and validates `text`, the contents of the manifest at `path` (named in errors).
    /// Format and version are checked first, so a manifest from another tool or a newer psscan
    /// fails with an error saying so rather than one about an unknown field; then come the
    /// structural checks of [`Manifest::validate`].
    pub fn parse(text: &str, path: &Path) -> Result<Manifest> {
        // Check format and version first, so a newer manifest gets a message about versions
        // rather than about some field this build does not know.
        let table: toml::Table = toml::from_str(text)
            .map_err(|e| Error::config(path, "syntax", e.message().to_string()))?;
        match table.get("format").and_then(|v| v.as_str()) {
            Some(FORMAT) => {}
            other => {
                return Err(Error::config(
                    path,
                    "format",
                    format!("expected \"{FORMAT}\", found {other:?}: not a psscan capture set"),
                ))
            }
        }
        match table.get("version").and_then(|v| v.as_integer()) {
            Some(v) if v == VERSION as i64 => {}
            other => {
                return Err(Error::config(
                    path,
                    "version",
                    format!(
                        "manifest version {other:?} is not supported by this psscan (reads \
                         version {VERSION}); upgrade psscan"
                    ),
                ))
            }
        }
        let manifest: Manifest = toml::from_str(text)
            .map_err(|e| Error::config(path, "manifest", e.message().to_string()))?;
        manifest.validate(path)?;
        Ok(manifest)
    }

    /// The manifest as pretty-printed TOML, as written to `manifest.toml`.
    pub fn to_toml_string(&self) -> String {
        toml::to_string_pretty(self).expect("a manifest always serialises")
    }

    /// Structural checks that need no files: names stay inside the set, light indices are
    /// unique, the image geometry is sane.
    pub fn validate(&self, path: &Path) -> Result<()> {
        let fail = |field: String, message: String| Err(Error::config(path, field, message));
        check_inside(&self.rig_file).or_else(|m| fail("rig_file".into(), m))?;
        if self.image.width == 0 || self.image.height == 0 {
            return fail(
                "image.width".into(),
                "image size must be at least 1x1".into(),
            );
        }
        if !(self.image.levels.white > self.image.levels.black
            && self.image.levels.black.is_finite())
        {
            return fail(
                "image.levels".into(),
                "the white level must lie above the black level".into(),
            );
        }
        if !(self.image.exposure.is_finite() && self.image.exposure > 0.0) {
            return fail("image.exposure".into(), "must be positive".into());
        }
        if !ENCODINGS.contains(&self.image.encoding.as_str()) {
            return fail(
                "image.encoding".into(),
                format!(
                    "unknown frame encoding \"{}\" (this psscan reads {})",
                    self.image.encoding,
                    ENCODINGS.join(", ")
                ),
            );
        }
        let mut seen_lights = std::collections::HashSet::new();
        let mut seen_files = std::collections::HashSet::new();
        let mut seen_dark = false;
        for (i, frame) in self.frames.iter().enumerate() {
            check_inside(&frame.file).or_else(|m| fail(format!("frames[{i}].file"), m))?;
            let normalised: std::path::PathBuf = Path::new(&frame.file)
                .components()
                .filter(|c| !matches!(c, Component::CurDir))
                .collect();
            if !seen_files.insert(normalised) {
                return fail(
                    format!("frames[{i}].file"),
                    format!("\"{}\" is listed for more than one frame", frame.file),
                );
            }
            match (frame.kind, frame.light) {
                (FrameKind::Light, Some(k)) => {
                    if !seen_lights.insert(k) {
                        return fail(
                            format!("frames[{i}].light"),
                            format!("light {k} appears twice"),
                        );
                    }
                }
                (FrameKind::Light, None) => {
                    return fail(
                        format!("frames[{i}].light"),
                        "a light frame needs its LED index".into(),
                    )
                }
                (FrameKind::Dark, Some(_)) => {
                    return fail(
                        format!("frames[{i}].light"),
                        "a dark frame has no LED".into(),
                    )
                }
                (FrameKind::Dark, None) => {
                    if seen_dark {
                        return fail(format!("frames[{i}]"), "more than one dark frame".into());
                    }
                    seen_dark = true;
                }
            }
        }
        Ok(())
    }

    /// The entry for LED `k`.
    pub fn light_frame(&self, k: usize) -> Option<&FrameEntry> {
        self.frames
            .iter()
            .find(|f| f.kind == FrameKind::Light && f.light == Some(k))
    }

    /// The dark frame's entry; `None` when the set has no dark frame.
    pub fn dark_frame(&self) -> Option<&FrameEntry> {
        self.frames.iter().find(|f| f.kind == FrameKind::Dark)
    }
}

/// A file name in a manifest must be a plain relative path inside the set: no `..`, no
/// absolute paths, no drive prefixes.
pub(crate) fn check_inside(name: &str) -> std::result::Result<(), String> {
    let path = Path::new(name);
    if name.is_empty() {
        return Err("empty file name".into());
    }
    for component in path.components() {
        match component {
            Component::Normal(_) | Component::CurDir => {}
            _ => {
                return Err(format!(
                    "\"{name}\" leaves the capture set's folder; names must be relative paths inside it"
                ))
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Manifest {
        Manifest {
            format: FORMAT.into(),
            version: VERSION,
            rig_file: "rig.toml".into(),
            calibration: None,
            image: ImageInfo {
                width: 4,
                height: 3,
                window: SensorWindow::FULL,
                levels: Levels {
                    black: 600.0,
                    white: 15600.0,
                },
                exposure: 1.0,
                encoding: "dn16".into(),
            },
            camera: CameraSettings {
                model: "test".into(),
                ..Default::default()
            },
            synthetic: None,
            frames: vec![
                FrameEntry {
                    kind: FrameKind::Dark,
                    light: None,
                    file: "dark.png".into(),
                    sha256: "00".into(),
                },
                FrameEntry {
                    kind: FrameKind::Light,
                    light: Some(0),
                    file: "L00.png".into(),
                    sha256: "11".into(),
                },
            ],
        }
    }

    #[test]
    fn round_trip() {
        let m = sample();
        let back = Manifest::parse(&m.to_toml_string(), Path::new("m.toml")).unwrap();
        assert_eq!(m, back);
        assert_eq!(back.light_frame(0).unwrap().file, "L00.png");
        assert!(back.dark_frame().is_some());
    }

    #[test]
    fn names_that_leave_the_set_are_refused() {
        for bad in ["../x.png", "/etc/passwd", "a/../../b.png", ""] {
            let mut m = sample();
            m.frames[1].file = bad.into();
            let err = Manifest::parse(&m.to_toml_string(), Path::new("m.toml"))
                .unwrap_err()
                .to_string();
            assert!(err.contains("frames[1].file"), "{bad}: {err}");
        }
    }

    #[test]
    fn unknown_versions_and_formats_are_refused_clearly() {
        let text = sample()
            .to_toml_string()
            .replace("version = 1", "version = 7");
        let err = Manifest::parse(&text, Path::new("m.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("version") && err.contains("7"), "{err}");
        let text = sample().to_toml_string().replace("psscan-capture", "other");
        let err = Manifest::parse(&text, Path::new("m.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("not a psscan capture set"), "{err}");
    }

    #[test]
    fn a_file_listed_twice_and_unknown_encodings_are_refused() {
        let mut m = sample();
        m.frames[1].file = "./dark.png".into();
        let err = Manifest::parse(&m.to_toml_string(), Path::new("m.toml"))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("frames[1].file") && err.contains("more than one"),
            "{err}"
        );

        let mut m = sample();
        m.image.encoding = "jpeg".into();
        let err = Manifest::parse(&m.to_toml_string(), Path::new("m.toml"))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("image.encoding") && err.contains("jpeg"),
            "{err}"
        );
        m.image.encoding = ENCODING_RAW.into();
        assert!(Manifest::parse(&m.to_toml_string(), Path::new("m.toml")).is_ok());
    }

    #[test]
    fn duplicate_lights_are_refused() {
        let mut m = sample();
        let mut dup = m.frames[1].clone();
        dup.file = "L00-again.png".into();
        m.frames.push(dup);
        let err = Manifest::parse(&m.to_toml_string(), Path::new("m.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("appears twice"), "{err}");
    }
}
