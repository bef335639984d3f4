//! Sets in the layout of the DiLiGenT photometric-stereo benchmark, so psscan's solver can be
//! compared with published methods on the same data:
//!
//! ```text
//! filenames.txt           one image file name per line (light k = line k)
//! light_directions.txt    one "x y z" per line, unit vectors toward the lights
//! light_intensities.txt   one "r g b" per line, the lights' relative intensities
//! mask.png                object mask (nonzero = object); optional
//! 001.png ...             16-bit RGB images, linear
//! Normal_gt.mat           ground-truth normals (MATLAB v5, variable Normal_gt, HxWx3); optional
//! ```
//!
//! **Coordinates.** DiLiGenT's frame is x to the right of the image, y up (toward the top of
//! the image), z toward the camera; light directions and normals are given in it. psscan's
//! world frame (DESIGN.md) is +x along image columns (right), +y toward the top of the image,
//! +z up toward the camera: the same axes. [`diligent_to_world`] is therefore the identity,
//! written out so the convention is stated once and tested (a flipped axis would show as a
//! large error against the ground truth). Image row 0 is the top row in both.

use std::path::{Path, PathBuf};

use rayon::prelude::*;

use super::set::read_inside;
use crate::error::{Error, Result};
use crate::plane::{Frames, LightFrame, Mask, Plane, SensorWindow};
use crate::progress::Progress;
use crate::raw::{decode_dn_frame, Levels};

/// The file listing the images, one file name per line; line `k` is light `k`.
pub const FILENAMES: &str = "filenames.txt";
/// The file of light directions, one `x y z` unit vector toward the light per line (DiLiGenT's
/// frame).
pub const LIGHT_DIRECTIONS: &str = "light_directions.txt";
/// The file of light intensities, one `r g b` relative intensity per line.
pub const LIGHT_INTENSITIES: &str = "light_intensities.txt";
/// The optional object mask (nonzero = object).
pub const MASK: &str = "mask.png";
/// The optional ground-truth normals (MATLAB v5 file).
pub const NORMAL_TRUTH: &str = "Normal_gt.mat";
/// The variable in [`NORMAL_TRUTH`] that holds the normals, an H x W x 3 array.
pub const NORMAL_TRUTH_VARIABLE: &str = "Normal_gt";

/// DiLiGenT images are 16-bit: 65535 is the white (saturation) level.
pub const LEVELS: Levels = Levels {
    black: 0.0,
    white: 65535.0,
};

/// A DiLiGenT (x right, y up, z toward the camera) vector in psscan's world frame (x right,
/// y toward the top of the image, z toward the camera): the same axes.
pub fn diligent_to_world(v: [f64; 3]) -> [f64; 3] {
    let [x, y, z] = v;
    [x, y, z]
}

/// A DiLiGenT-layout set opened for reading.
#[derive(Clone, Debug)]
pub struct DiligentSet {
    /// The set's folder.
    pub dir: PathBuf,
    /// The image file names from [`FILENAMES`], in light order, relative to `dir`.
    pub files: Vec<String>,
    /// Unit directions toward the lights, in psscan's world frame.
    pub directions: Vec<[f64; 3]>,
    /// Per light, its relative R, G, B intensity from [`LIGHT_INTENSITIES`] (each positive).
    pub intensities: Vec<[f64; 3]>,
}

impl DiligentSet {
    /// True when `dir` looks like a DiLiGenT-layout set.
    pub fn is_diligent(dir: &Path) -> bool {
        dir.join(FILENAMES).is_file() && dir.join(LIGHT_DIRECTIONS).is_file()
    }

    /// Reads the three text files and checks they agree.
    pub fn open(dir: &Path) -> Result<DiligentSet> {
        let files: Vec<String> = read_text(dir, FILENAMES)?
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .map(String::from)
            .collect();
        if files.len() < 3 {
            return Err(Error::capture_set(
                dir,
                format!(
                    "{FILENAMES} lists {} images; photometric stereo needs at least 3",
                    files.len()
                ),
            ));
        }
        let directions = read_triples(dir, LIGHT_DIRECTIONS)?;
        let intensities = read_triples(dir, LIGHT_INTENSITIES)?;
        for (name, n) in [
            (LIGHT_DIRECTIONS, directions.len()),
            (LIGHT_INTENSITIES, intensities.len()),
        ] {
            if n != files.len() {
                return Err(Error::capture_set(
                    dir,
                    format!(
                        "{name} has {n} rows but {FILENAMES} lists {} images",
                        files.len()
                    ),
                ));
            }
        }
        for (k, d) in directions.iter().enumerate() {
            let norm = d.iter().map(|v| v * v).sum::<f64>().sqrt();
            if !(norm > 0.5 && norm < 2.0) {
                return Err(Error::config(
                    dir.join(LIGHT_DIRECTIONS),
                    format!("line {}", k + 1),
                    format!("{d:?} is not a unit direction"),
                ));
            }
        }
        for (k, i) in intensities.iter().enumerate() {
            if i.iter().any(|v| v.is_nan() || *v <= 0.0) {
                return Err(Error::config(
                    dir.join(LIGHT_INTENSITIES),
                    format!("line {}", k + 1),
                    format!("intensity {i:?} must be positive"),
                ));
            }
        }
        Ok(DiligentSet {
            dir: dir.to_path_buf(),
            files,
            directions: directions.into_iter().map(diligent_to_world).collect(),
            intensities,
        })
    }

    /// Decodes every image (in parallel) into linear planes, 1.0 = 65535; a pixel with a
    /// channel at 65535 is saturated.
    pub fn load_frames(&self, progress: &dyn Progress) -> Result<Frames> {
        progress.begin("decode", self.files.len() as u64);
        // Decoded and linearised together, in parallel (see `decode_dn_frame`).
        let images = self
            .files
            .par_iter()
            .map(|name| {
                let (path, bytes) = read_inside(&self.dir, name)?;
                let (frame, size) = decode_dn_frame(&bytes, &path, &LEVELS)?;
                progress.advance(1);
                Ok((path, frame, size))
            })
            .collect::<Result<Vec<_>>>()?;
        progress.end();
        let (width, height) = images[0].2;
        let lights = images
            .into_iter()
            .map(|(path, frame, (w, h))| {
                if (w, h) != (width, height) {
                    return Err(Error::image(
                        &path,
                        format!("is {w}x{h}, the first image is {width}x{height}"),
                    ));
                }
                Ok(frame)
            })
            .collect::<Result<Vec<LightFrame>>>()?;
        Ok(Frames {
            width,
            height,
            window: SensorWindow::FULL,
            lights,
        })
    }

    /// The object mask, when the set has one; it must be `width x height`.
    pub fn mask(&self, width: usize, height: usize) -> Result<Option<Mask>> {
        if !self.dir.join(MASK).exists() {
            return Ok(None);
        }
        let (path, bytes) = read_inside(&self.dir, MASK)?;
        let image = image::load_from_memory(&bytes)
            .map_err(|e| Error::image(&path, e))?
            .into_luma16();
        if (image.width() as usize, image.height() as usize) != (width, height) {
            return Err(Error::image(
                &path,
                format!(
                    "is {}x{}, the images are {width}x{height}",
                    image.width(),
                    image.height()
                ),
            ));
        }
        Ok(Some(Mask {
            width,
            height,
            data: image.into_raw().into_iter().map(|v| v > 0).collect(),
        }))
    }

    /// The ground-truth normals (psscan's world frame), when the set has them.
    pub fn normal_truth(&self, width: usize, height: usize) -> Result<Option<[Plane; 3]>> {
        if !self.dir.join(NORMAL_TRUTH).exists() {
            return Ok(None);
        }
        let (path, bytes) = read_inside(&self.dir, NORMAL_TRUTH)?;
        read_normal_mat(&bytes, width, height)
            .map(Some)
            .map_err(|m| Error::image(&path, m))
    }
}

fn read_text(dir: &Path, name: &str) -> Result<String> {
    let (path, bytes) = read_inside(dir, name)?;
    String::from_utf8(bytes).map_err(|_| Error::image(&path, "is not UTF-8 text"))
}

/// Rows of three numbers separated by spaces, tabs or commas; blank lines are skipped.
fn read_triples(dir: &Path, name: &str) -> Result<Vec<[f64; 3]>> {
    let text = read_text(dir, name)?;
    let mut rows = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let fields: Vec<&str> = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|f| !f.is_empty())
            .collect();
        if fields.is_empty() {
            continue;
        }
        let values: Option<Vec<f64>> = fields
            .iter()
            .map(|f| f.parse::<f64>().ok().filter(|v| v.is_finite()))
            .collect();
        match values {
            Some(v) if v.len() == 3 => rows.push([v[0], v[1], v[2]]),
            _ => {
                return Err(Error::config(
                    dir.join(name),
                    format!("line {}", n + 1),
                    format!("expected three numbers, found \"{}\"", line.trim()),
                ))
            }
        }
    }
    Ok(rows)
}

/// The `Normal_gt` variable of a MATLAB v5 file: `height x width x 3`, column-major (MATLAB's
/// order), turned into three row-major planes.
fn read_normal_mat(
    bytes: &[u8],
    width: usize,
    height: usize,
) -> std::result::Result<[Plane; 3], String> {
    let parsed = std::panic::catch_unwind(|| matfile::MatFile::parse(bytes))
        .map_err(|_| "the MATLAB file reader failed on this file (corrupt?)".to_string())?
        .map_err(|e| format!("not a readable MATLAB v5 file: {e}"))?;
    let array = parsed
        .find_by_name(NORMAL_TRUTH_VARIABLE)
        .ok_or_else(|| format!("holds no variable {NORMAL_TRUTH_VARIABLE}"))?;
    if array.size() != &vec![height, width, 3] {
        return Err(format!(
            "{NORMAL_TRUTH_VARIABLE} is {:?}, expected [{height}, {width}, 3]",
            array.size()
        ));
    }
    let values: Vec<f64> = match array.data() {
        matfile::NumericData::Double { real, .. } => real.clone(),
        matfile::NumericData::Single { real, .. } => real.iter().map(|&v| v as f64).collect(),
        _ => return Err(format!("{NORMAL_TRUTH_VARIABLE} is not a float array")),
    };
    if values.len() != width * height * 3 {
        return Err(format!(
            "{NORMAL_TRUTH_VARIABLE} holds {} values",
            values.len()
        ));
    }
    let mut planes: [Plane; 3] = std::array::from_fn(|_| Plane::new(width, height, 0.0));
    for y in 0..height {
        for x in 0..width {
            let at = |c: usize| values[y + height * (x + width * c)];
            let n = diligent_to_world([at(0), at(1), at(2)]);
            for c in 0..3 {
                planes[c].data[y * width + x] = n[c] as f32;
            }
        }
    }
    Ok(planes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bunny(variant: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../shared/data/bunny-diligent")
            .join(variant)
    }

    #[test]
    #[ignore = "reads ../shared/data: run by make eval"]
    fn the_bunny_set_reads_with_its_mask_and_truth() {
        let dir = bunny("bunny_lambert_noshadow");
        assert!(DiligentSet::is_diligent(&dir));
        let set = DiligentSet::open(&dir).unwrap();
        assert_eq!(set.files.len(), 50);
        let mask = set.mask(256, 256).unwrap().unwrap();
        assert_eq!(mask.count(), 20317);
        let truth = set.normal_truth(256, 256).unwrap().unwrap();
        // Unit normals inside the mask, zero outside; facing the camera (z > 0).
        for i in 0..256 * 256 {
            let n = [truth[0].data[i], truth[1].data[i], truth[2].data[i]];
            let len = n.iter().map(|v| v * v).sum::<f32>().sqrt();
            if mask.data[i] {
                assert!((len - 1.0).abs() < 1e-4 && n[2] >= 0.0, "{i}: {n:?}");
            }
        }
    }

    /// A DiLiGenT-layout folder's three text files for `n` lights (no images): the first
    /// direction is the bunny set's first, so its value can be damaged by name.
    fn write_text_files(dir: &Path, n: usize) {
        let names: Vec<String> = (1..=n).map(|k| format!("{k:03}.png")).collect();
        std::fs::write(dir.join(FILENAMES), names.join("\n")).unwrap();
        let directions: Vec<String> = (0..n)
            .map(|k| match k {
                0 => "0.959493 0.134231 0.247710".to_string(),
                _ => {
                    let a = k as f64 * 0.7;
                    format!("{:.6} {:.6} {:.6}", 0.4 * a.cos(), 0.4 * a.sin(), 0.916515)
                }
            })
            .collect();
        std::fs::write(dir.join(LIGHT_DIRECTIONS), directions.join("\n")).unwrap();
        std::fs::write(dir.join(LIGHT_INTENSITIES), vec!["1 1 1"; n].join("\n")).unwrap();
    }

    #[test]
    fn inconsistent_text_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        write_text_files(dir.path(), 50);
        let good = DiligentSet::open(dir.path()).unwrap();

        let text = std::fs::read_to_string(dir.path().join(LIGHT_DIRECTIONS)).unwrap();
        let short: Vec<&str> = text.lines().take(49).collect();
        std::fs::write(dir.path().join(LIGHT_DIRECTIONS), short.join("\n")).unwrap();
        let err = DiligentSet::open(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains(LIGHT_DIRECTIONS) && err.contains("49 rows"),
            "{err}"
        );

        std::fs::write(
            dir.path().join(LIGHT_DIRECTIONS),
            text.replace("0.959493", "x"),
        )
        .unwrap();
        let err = DiligentSet::open(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains(LIGHT_DIRECTIONS) && err.contains("line 1"),
            "{err}"
        );

        let set = DiligentSet {
            files: vec!["../001.png".into(); 3],
            ..good
        };
        let err = set
            .load_frames(&crate::progress::Silent)
            .unwrap_err()
            .to_string();
        assert!(err.contains("leaves the capture set"), "{err}");
    }

    /// A MATLAB v5 file holding one uncompressed double array `Normal_gt` of size `dims`
    /// (a reader check independent of the real sets; tests/cli_diligent_generated.rs writes
    /// whole sets this way).
    fn normal_mat(dims: [i32; 3]) -> Vec<u8> {
        fn element(out: &mut Vec<u8>, kind: u32, payload: &[u8]) {
            out.extend_from_slice(&kind.to_le_bytes());
            out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
            out.extend_from_slice(payload);
            out.resize(out.len().next_multiple_of(8), 0);
        }
        let count = dims.iter().product::<i32>() as usize;
        let mut body = Vec::new();
        element(&mut body, 6, &[6u8, 0, 0, 0, 0, 0, 0, 0]); // flags: double class
        let dims: Vec<u8> = dims.iter().flat_map(|d| d.to_le_bytes()).collect();
        element(&mut body, 5, &dims);
        element(&mut body, 1, NORMAL_TRUTH_VARIABLE.as_bytes());
        let values: Vec<u8> = (0..count).flat_map(|_| 0.5f64.to_le_bytes()).collect();
        element(&mut body, 9, &values);
        let mut file = b"MATLAB 5.0 MAT-file".to_vec();
        file.resize(124, b' ');
        file.extend_from_slice(&0x0100u16.to_le_bytes());
        file.extend_from_slice(b"IM");
        element(&mut file, 14, &body);
        file
    }

    #[test]
    fn a_broken_truth_file_is_named() {
        assert!(read_normal_mat(b"MATLAB 5.0 MAT-file, garbage", 4, 4).is_err());
        let bytes = normal_mat([16, 16, 3]);
        assert!(read_normal_mat(&bytes, 16, 16).is_ok());
        let err = read_normal_mat(&bytes, 8, 16).unwrap_err();
        assert!(err.contains("[16, 8, 3]"), "{err}");
        assert!(read_normal_mat(&bytes[..bytes.len() / 3], 16, 16).is_err());
    }
}
