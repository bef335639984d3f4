//! From a solve to an engine-ready material (`psscan derive`): flattening, height, seamless
//! tiling, normal and roughness mip chains with specular antialiasing, engine encodings of the
//! normal map (OpenGL or DirectX, 8 or 16 bit, two-channel XY), DDS files (BC5 normals, BC7
//! albedo, BC4 roughness, full mip chains) and a glTF 2.0 material on a quad of the sample's
//! physical size. Every step is optional; they run in that order on one set of maps, so a
//! tiled material has tiled heights, mips and textures.

pub mod dds;
pub mod fft;
pub mod flatten;
pub mod gltf;
pub mod height;
pub mod mips;
pub mod outputs;
pub mod poisson;
pub mod source;
pub mod tiling;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use crate::error::{Error, Result};
use crate::fsutil::{write_atomic, StagedDir};
use crate::plane::Plane;
use crate::progress::Progress;
use crate::solve::SheenModel;

pub use mips::RoughnessFilter;
pub use source::SolvedMaps;

use super::NormalConvention;

/// The file that marks a finished derive folder.
pub const DERIVE_REPORT: &str = "derive.json";

/// A length on the sample: millimetres (needs the solve's scale) or pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Length {
    /// Millimetres on the sample.
    Mm(f64),
    /// Pixels of the map.
    Px(f64),
}

impl Length {
    /// Parses `12mm`, `40px` or a bare number of pixels.
    pub fn parse(text: &str) -> std::result::Result<Length, String> {
        let t = text.trim();
        let (number, unit) = if let Some(n) = t.strip_suffix("mm") {
            (n, "mm")
        } else if let Some(n) = t.strip_suffix("px") {
            (n, "px")
        } else {
            (t, "px")
        };
        let v: f64 = number
            .trim()
            .parse()
            .map_err(|_| format!("\"{text}\" is not a length (for example 12mm or 40px)"))?;
        if !(v.is_finite() && v > 0.0) {
            return Err(format!("\"{text}\": a length must be positive"));
        }
        Ok(if unit == "mm" {
            Length::Mm(v)
        } else {
            Length::Px(v)
        })
    }

    /// In pixels; millimetres need `pixel_mm`, and fail naming the step when it is unknown.
    pub fn to_px(self, pixel_mm: Option<f64>, what: &str) -> Result<f64> {
        match (self, pixel_mm) {
            (Length::Px(v), _) => Ok(v),
            (Length::Mm(v), Some(mm)) => Ok(v / mm),
            (Length::Mm(_), None) => Err(Error::Invalid(format!(
                "{what} is given in mm but the solve has no scale (its report.json has no \
                 pixel_size_mm): give it in px, or pass --pixel-mm"
            ))),
        }
    }
}

/// How to tile: a repeat the user chose, or the weave's period found in the albedo.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum TileChoice {
    /// A repeat of the given width and height.
    Repeat {
        /// The repeat's width, along image rows.
        width: Length,
        /// The repeat's height, along image columns.
        height: Length,
    },
    /// The weave's period, found as the strongest repeat of the albedo's autocorrelation.
    Auto,
}

/// Specular antialiasing of the roughness mips.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct RoughnessOptions {
    /// How each level's roughness is widened for the normals it averages.
    pub filter: RoughnessFilter,
    /// The material's GGX roughness (alpha = roughness^2, as in glTF) at full resolution.
    pub base: f64,
}

/// What `derive` makes. `Default` makes nothing but the report; the CLI turns flags on.
#[derive(Clone, Debug, Serialize)]
pub struct DeriveOptions {
    /// Cut-off radius of the flattening (detail shorter than this is kept).
    pub flatten: Option<Length>,
    /// Cut one seamless tile before the later steps; `None` keeps the whole map.
    pub tile: Option<TileChoice>,
    /// Integrate the normals into a height field (`height.exr`, `height.png`).
    pub height: bool,
    /// Roughness mips with specular antialiasing; `None` makes none.
    pub roughness: Option<RoughnessOptions>,
    /// Normal-map PNGs (`normal.png`, `normal_xy.png`) and `albedo.png` in these encodings.
    pub textures: bool,
    /// The normal maps' Y convention (OpenGL +Y up or DirectX +Y down), in the textures and the DDS
    /// files.
    pub convention: NormalConvention,
    /// 8 or 16.
    pub bits: u8,
    /// Write DDS files with full mip chains (BC5 normals, BC7 albedo, BC4 roughness).
    pub dds: bool,
    /// Write the glTF material; it needs the sample's scale (the solve's or `pixel_mm`).
    pub gltf: bool,
    /// Millimetres per pixel on the sample, overriding (or standing in for) the solve's.
    pub pixel_mm: Option<f64>,
}

impl Default for DeriveOptions {
    fn default() -> Self {
        DeriveOptions {
            flatten: None,
            tile: None,
            height: false,
            roughness: None,
            textures: false,
            convention: NormalConvention::OpenGl,
            bits: 16,
            dds: false,
            gltf: false,
            pixel_mm: None,
        }
    }
}

impl DeriveOptions {
    /// Every output, the defaults the CLI's `--all` uses.
    pub fn all() -> Self {
        DeriveOptions {
            flatten: Some(Length::Mm(10.0)),
            tile: None,
            height: true,
            roughness: Some(RoughnessOptions {
                filter: RoughnessFilter::Vmf,
                base: 0.5,
            }),
            textures: true,
            dds: true,
            gltf: true,
            ..DeriveOptions::default()
        }
    }

    fn validate(&self) -> Result<()> {
        if self.bits != 8 && self.bits != 16 {
            return Err(Error::Invalid(format!(
                "texture bits per channel must be 8 or 16, got {}",
                self.bits
            )));
        }
        if let Some(r) = &self.roughness {
            if !(r.base > 0.0 && r.base <= 1.0) {
                return Err(Error::Invalid(format!(
                    "base roughness must be in (0, 1], got {}",
                    r.base
                )));
            }
        }
        if let Some(mm) = self.pixel_mm {
            if !(mm.is_finite() && mm > 0.0) {
                return Err(Error::Invalid(format!(
                    "the pixel size on the sample must be positive (mm), got {mm}"
                )));
            }
        }
        Ok(())
    }
}

/// Where the maps come from.
pub enum DeriveSource<'a> {
    /// A finished solve folder (report.json, normal.exr, albedo.exr, confidence.exr).
    SolveDir(&'a Path),
    /// Maps already in memory (the `solve` command, tests).
    Maps(Box<SolvedMaps>),
}

/// What `derive` did: figures per step, seconds per step, the files written.
#[derive(Clone, Debug, Default, Serialize)]
pub struct DeriveReport {
    /// Width of the derived maps in pixels (the tile's, when tiled).
    pub width: usize,
    /// Height of the derived maps in pixels (the tile's, when tiled).
    pub height: usize,
    /// Millimetres per pixel, and where that came from (`report.json`, `--pixel-mm`); absent
    /// when unknown (heights are then in pixel units and mm lengths are refused).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pixel_mm: Option<f64>,
    /// Where `pixel_mm` came from (`report.json`, the rig, `--pixel-mm`), or why it is unknown.
    pub scale_source: String,
    /// The flattening's cut-off radius converted to pixels; absent when not flattened.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub flatten_radius_px: Option<f64>,
    /// What tiling did; absent when not tiled.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tiling: Option<tiling::TilingReport>,
    /// The height field's units and range; absent when no height was made.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height_map: Option<HeightReport>,
    /// Mean roughness per mip level and the filter used; absent when no roughness was made.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub roughness: Option<mips::RoughnessReport>,
    /// The cloth lobe mapped to KHR_materials_sheen, when the solve fitted it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sheen: Option<gltf::SheenParams>,
    /// Wall-clock seconds of each step that ran, by step name (`load`, `flatten`, ..., `total`).
    pub timings_s: BTreeMap<String, f64>,
    /// The files written, by file name, with their path in the output folder.
    pub outputs: BTreeMap<String, PathBuf>,
}

/// What the height step wrote (`height.exr`, `height.png`): the height field's units and range.
#[derive(Clone, Debug, Serialize)]
pub struct HeightReport {
    /// `mm` where the scale is known, else `px`.
    pub units: String,
    /// Lowest height, in `units` (mapped to black in `height.png`).
    pub min: f64,
    /// Highest height, in `units` (mapped to white in `height.png`).
    pub max: f64,
    /// How the masked least-squares refinement ended, where some pixels were not solved
    /// (their height is 0); absent when the whole map was integrated in the Fourier domain.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub masked: Option<poisson::MaskedSolve>,
}

/// Runs the requested steps on `source` and writes the results into `out` (staged: a folder
/// appears complete or not at all; an existing one is replaced only with `force`).
pub fn derive(
    source: DeriveSource<'_>,
    out: &Path,
    options: &DeriveOptions,
    force: bool,
    progress: &dyn Progress,
) -> Result<DeriveReport> {
    options.validate()?;
    let total = Instant::now();
    let mut timings = BTreeMap::new();
    let start = Instant::now();
    // The solve folder is this run's input: the output may not be, hold or sit inside it.
    let input_dir = match &source {
        DeriveSource::SolveDir(dir) => Some(dir.to_path_buf()),
        DeriveSource::Maps(_) => None,
    };
    let inputs: Vec<&Path> = input_dir.iter().map(|p| p.as_path()).collect();
    let mut maps = match source {
        DeriveSource::SolveDir(dir) => source::load(dir)?,
        DeriveSource::Maps(m) => *m,
    };
    timings.insert("load".to_string(), start.elapsed().as_secs_f64());
    let stage = StagedDir::create(out, force, &inputs)?;
    let mut report = DeriveReport {
        scale_source: maps.scale_source.clone(),
        ..DeriveReport::default()
    };
    if let Some(mm) = options.pixel_mm {
        maps.pixel_mm = Some(mm);
        report.scale_source = "given to derive (overrides the solve's report)".into();
    }
    report.pixel_mm = maps.pixel_mm;
    let dir = stage.path();
    let mut step = |name: &str, f: &mut dyn FnMut() -> Result<()>| -> Result<()> {
        progress.begin(name, 1);
        let start = Instant::now();
        f()?;
        timings.insert(name.to_string(), start.elapsed().as_secs_f64());
        progress.advance(1);
        progress.end();
        Ok(())
    };

    if let Some(radius) = options.flatten {
        let px = radius.to_px(maps.pixel_mm, "the flattening radius")?;
        report.flatten_radius_px = Some(px);
        step("flatten", &mut || {
            flatten::flatten(&mut maps.normal, &maps.solved, px);
            Ok(())
        })?;
    }
    if let Some(choice) = options.tile {
        step("tile", &mut || {
            report.tiling = Some(tiling::tile(&mut maps, choice)?);
            Ok(())
        })?;
    }
    let mut height_plane = None;
    if options.height {
        step("height", &mut || {
            let boundary = if report.tiling.is_some() {
                height::Boundary::Periodic
            } else {
                height::Boundary::Mirrored
            };
            let (z, masked) = height::integrate_over(
                &maps.normal,
                &maps.solved,
                maps.pixel_mm.unwrap_or(1.0),
                boundary,
            );
            let mut written = outputs::write_height(dir, &z, maps.pixel_mm.is_some())?;
            written.masked = masked;
            report.height_map = Some(written);
            height_plane = Some(z);
            Ok(())
        })?;
    }
    let mut chain = None;
    if options.roughness.is_some() || options.dds || options.gltf {
        step("mips", &mut || {
            chain = Some(mips::MipChain::build(&maps.normal));
            Ok(())
        })?;
    }
    let mut roughness_levels: Option<Vec<Plane>> = None;
    if let (Some(r), Some(chain)) = (&options.roughness, &chain) {
        step("roughness", &mut || {
            let levels = chain.roughness(r.filter, r.base);
            report.roughness = Some(mips::RoughnessReport::new(r, &levels));
            // The roughness mips are this step's product: with --dds they go into the DDS
            // step's files, without it into roughness.dds alone.
            if !options.dds {
                dds::write_roughness(dir, &levels)?;
            }
            roughness_levels = Some(levels);
            Ok(())
        })?;
    }
    if options.textures {
        step("textures", &mut || {
            outputs::write_textures(dir, &maps, options.convention, options.bits)
        })?;
    }
    if let (true, Some(chain)) = (options.dds, &chain) {
        step("dds", &mut || {
            dds::write_all(
                dir,
                chain,
                &maps,
                options.convention,
                roughness_levels.as_deref(),
            )
        })?;
    }
    if options.gltf {
        step("gltf", &mut || {
            let base = options.roughness.map_or(1.0, |r| r.base);
            report.sheen = gltf::write(dir, &maps, base)?;
            Ok(())
        })?;
    }
    drop(height_plane);
    report.width = maps.width();
    report.height = maps.height();
    report.outputs = list_outputs(dir, out)?;
    timings.insert("total".to_string(), total.elapsed().as_secs_f64());
    report.timings_s = timings;
    let json = serde_json::to_string_pretty(&report).expect("a derive report always serialises");
    write_atomic(&dir.join(DERIVE_REPORT), json.as_bytes())?;
    stage.commit(force, &inputs)?;
    Ok(report)
}

/// The files in the staging folder, by name, under their final folder.
fn list_outputs(stage: &Path, out: &Path) -> Result<BTreeMap<String, PathBuf>> {
    let mut files = BTreeMap::new();
    for entry in std::fs::read_dir(stage).map_err(|e| Error::io(stage, e))? {
        let entry = entry.map_err(|e| Error::io(stage, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        files.insert(name.clone(), out.join(name));
    }
    Ok(files)
}

/// The sheen lobe the solve fitted, if it fitted one anywhere.
pub fn fitted_sheen(maps: &SolvedMaps) -> Option<SheenModel> {
    maps.sheen.filter(|_| maps.sheen_pixels > 0)
}

/// Test helper: three planes (a normal field) of `w` x `h` from a function of the pixel.
#[cfg(test)]
pub(crate) fn normal_field(w: usize, h: usize, f: impl Fn(usize, usize) -> [f64; 3]) -> [Plane; 3] {
    let mut out = [
        Plane::new(w, h, 0.0),
        Plane::new(w, h, 0.0),
        Plane::new(w, h, 0.0),
    ];
    for y in 0..h {
        for x in 0..w {
            let n = f(x, y);
            for c in 0..3 {
                out[c].data[y * w + x] = n[c] as f32;
            }
        }
    }
    out
}
