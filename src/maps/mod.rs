//! Everything derived from a solve, and the writers: normal maps (16-bit PNG in OpenGL or
//! DirectX convention, float EXR), albedo (16-bit sRGB PNG, linear EXR), the confidence map
//! (EXR: residual, predicted error, condition, lights used, status, which fit: 0 least
//! squares, 1 robust, 2 sheen) and `report.json`.

pub mod derive;
pub mod encode;
pub mod html;
pub mod report;
pub mod srgb;

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::Serialize;

use crate::error::{Error, Result};
use crate::fsutil::{create_dir_all, AtomicFile};
use crate::io::{ExrCompression, ExrSamples};
use crate::solve::SolveResult;
use crate::timing::Busy;

pub use crate::io::PngCompression;
pub use encode::NormalConvention;
pub use report::Report;

/// Which maps to write and how.
#[derive(Clone, Debug, Serialize)]
pub struct MapOptions {
    /// The Y convention of the normal maps written (PNG and EXR).
    pub normal_convention: NormalConvention,
    /// Write the 16-bit PNG maps (`normal.png`, `albedo.png`).
    pub png: bool,
    /// Write the float EXR maps (`normal.exr`, `albedo.exr`); `confidence.exr` is written either
    /// way.
    pub exr: bool,
    /// Camera RGB to linear sRGB for the display output (`albedo.png`); the solve's data
    /// outputs (EXR) stay in the camera's white-balanced RGB. `None`: the channels are sRGB's.
    pub display_matrix: Option<[[f64; 3]; 3]>,
    /// Write `report.html` (and the frame previews it shows) beside the maps.
    pub report_html: bool,
    /// Deflate effort of the PNG maps.
    pub png_compression: PngCompression,
}

impl Default for MapOptions {
    fn default() -> Self {
        MapOptions {
            normal_convention: NormalConvention::OpenGl,
            png: true,
            exr: true,
            display_matrix: None,
            report_html: true,
            png_compression: PngCompression::Fast,
        }
    }
}

/// Paths of the files written (absent when not requested).
#[derive(Clone, Debug, Default, Serialize)]
pub struct WrittenMaps {
    /// `normal.png`, 16-bit RGB.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_png: Option<PathBuf>,
    /// `normal.exr`, float RGB.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_exr: Option<PathBuf>,
    /// `albedo.png`, 16-bit sRGB.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub albedo_png: Option<PathBuf>,
    /// `albedo.exr`, linear white-balanced camera RGB.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub albedo_exr: Option<PathBuf>,
    /// `confidence.exr`, always written.
    pub confidence_exr: PathBuf,
}

/// The solve report's file name; its presence marks a folder holding a finished solve.
pub const REPORT_FILE: &str = "report.json";

/// Refuses to write into a folder that already holds a finished solve, unless `force`.
pub fn prepare_output_dir(dir: &Path, force: bool) -> Result<()> {
    let report = dir.join(REPORT_FILE);
    if report.exists() && !force {
        return Err(Error::Exists { path: report });
    }
    create_dir_all(dir)
}

/// Writes the maps of `result` into `dir` (each file atomically; the files are encoded in
/// parallel, one per core, and the EXR encoder compresses its blocks in parallel too).
pub fn write_maps(result: &SolveResult, dir: &Path, options: &MapOptions) -> Result<WrittenMaps> {
    write_maps_timed(result, dir, options, &Busy::new(&MAP_STAGES))
}

/// The stages [`write_maps_timed`] records: each map encoded straight into its file
/// ("write"), then flushed to disk and renamed into place ("sync").
pub const MAP_STAGES: [&str; 10] = [
    "write normal.png",
    "sync normal.png",
    "write albedo.png",
    "sync albedo.png",
    "write normal.exr",
    "sync normal.exr",
    "write albedo.exr",
    "sync albedo.exr",
    "write confidence.exr",
    "sync confidence.exr",
];

/// The least map size (pixels) whose files are written past the page cache
/// ([`AtomicFile::create_uncached`]): from there a solve writes tens of megabytes or more, which
/// the kernel would first copy into pages it must take and clear. A small map's files cost
/// little either way, and buffered they do not wait for the disk.
const UNCACHED_MAP_MIN_PIXELS: usize = 1 << 20;

/// One map file to write: its name, and whether it is asked for.
#[derive(Clone, Copy, PartialEq)]
enum MapFile {
    NormalPng,
    AlbedoPng,
    NormalExr,
    AlbedoExr,
    Confidence,
}

impl MapFile {
    fn name(self) -> &'static str {
        match self {
            MapFile::NormalPng => "normal.png",
            MapFile::AlbedoPng => "albedo.png",
            MapFile::NormalExr => "normal.exr",
            MapFile::AlbedoExr => "albedo.exr",
            MapFile::Confidence => "confidence.exr",
        }
    }
}

/// [`write_maps`], adding each map's encode and write time to `busy` (which holds
/// [`MAP_STAGES`]).
pub fn write_maps_timed(
    result: &SolveResult,
    dir: &Path,
    options: &MapOptions,
    busy: &Busy,
) -> Result<WrittenMaps> {
    let mut files = vec![MapFile::Confidence];
    if options.png {
        files.extend([MapFile::NormalPng, MapFile::AlbedoPng]);
    }
    if options.exr {
        files.extend([MapFile::NormalExr, MapFile::AlbedoExr]);
    }
    // Each map is encoded straight into its (temporary) file, and flushed to disk on a
    // thread of its own: a rayon worker waiting for the disk would leave a core idle while
    // other maps still encode.
    let written = std::thread::scope(|scope| {
        let writers = files
            .par_iter()
            .map(|&file| {
                let path = dir.join(file.name());
                let mut out = if result.width * result.height >= UNCACHED_MAP_MIN_PIXELS {
                    AtomicFile::create_uncached(&path)?
                } else {
                    AtomicFile::create(&path)?
                };
                busy.time(&format!("write {}", file.name()), || {
                    encode_map_into(out.writer(), result, file, &path, options)
                })?;
                let syncer = scope.spawn(move || {
                    busy.time(&format!("sync {}", file.name()), || out.commit())?;
                    Ok((file, path))
                });
                Ok(syncer)
            })
            .collect::<Vec<Result<_>>>();
        // The first failure (of an encode or a write) is returned; the scope joins every
        // writer before it ends, so none outlives this function.
        writers
            .into_iter()
            .map(|w| w.and_then(|w| w.join().expect("a map writer panicked")))
            .collect::<Result<Vec<(MapFile, PathBuf)>>>()
    })?;
    let find = |f: MapFile| {
        written
            .iter()
            .find(|(k, _)| *k == f)
            .map(|(_, p)| p.clone())
    };
    Ok(WrittenMaps {
        normal_png: find(MapFile::NormalPng),
        normal_exr: find(MapFile::NormalExr),
        albedo_png: find(MapFile::AlbedoPng),
        albedo_exr: find(MapFile::AlbedoExr),
        confidence_exr: find(MapFile::Confidence).expect("the confidence map is always written"),
    })
}

/// One map's file bytes, written to `out`.
fn encode_map_into(
    out: &mut (impl std::io::Write + std::io::Seek),
    result: &SolveResult,
    file: MapFile,
    path: &Path,
    options: &MapOptions,
) -> Result<()> {
    let (w, h) = (result.width, result.height);
    match file {
        MapFile::NormalPng => crate::io::encode_png16_rows_into(
            out,
            path,
            w,
            h,
            &encode::normal_rows16(result, options.normal_convention),
            options.png_compression,
        ),
        MapFile::AlbedoPng => crate::io::encode_png16_rows_into(
            out,
            path,
            w,
            h,
            &encode::albedo_rows16(result, options.display_matrix.as_ref()),
            options.png_compression,
        ),
        MapFile::NormalExr => {
            let [nx, ny, nz] = encode::normal_planes(result, options.normal_convention);
            let channels = [("R", &*nx), ("G", &*ny), ("B", &*nz)];
            crate::io::encode_exr_planes_into(out, path, &channels, ExrCompression::None)
        }
        MapFile::AlbedoExr => {
            let [r, g, b] = &result.albedo;
            let channels = [("R", r), ("G", g), ("B", b)];
            crate::io::encode_exr_planes_into(out, path, &channels, ExrCompression::None)
        }
        MapFile::Confidence => {
            let channels = vec![
                (
                    "residual",
                    ExrSamples::F32(Cow::Borrowed(&result.residual.data)),
                ),
                (
                    "predicted_error_deg",
                    ExrSamples::F32(Cow::Borrowed(&result.predicted_error_deg.data)),
                ),
                (
                    "condition",
                    ExrSamples::F32(Cow::Borrowed(&result.condition.data)),
                ),
                (
                    "lights_used",
                    ExrSamples::small_integers(result.lights_used.iter().map(|&v| v as u16)),
                ),
                (
                    "status",
                    ExrSamples::small_integers(result.status.iter().map(|&s| s as u16)),
                ),
                (
                    "fit",
                    ExrSamples::small_integers(result.fit.iter().map(|&f| f as u16)),
                ),
            ];
            // The class and count channels in half precision (whole numbers, exact), all
            // stored as they are: 16 MP takes 290 MB, where RLE over six f32 channels took
            // 265 MB and most of a second to encode.
            crate::io::encode_exr_samples_into(out, path, (w, h), channels, ExrCompression::None)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::PixelStatus;

    /// A map large enough to be written past the page cache, in several of its blocks: each
    /// file holds the bytes its encoder writes into memory.
    #[test]
    fn large_maps_written_past_the_page_cache_are_the_encoders_bytes() {
        let (w, h) = (1024, 1024 + 37);
        assert!(w * h >= UNCACHED_MAP_MIN_PIXELS);
        let mut result = SolveResult::new(w, h);
        let mut state = 7u32;
        let mut next = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32
        };
        for i in 0..w * h {
            for c in 0..3 {
                result.normal[c].data[i] = next() * 2.0 - 1.0;
                result.albedo[c].data[i] = next();
            }
            result.residual.data[i] = next();
            result.lights_used[i] = (i % 11) as u8;
            if i % 9 != 0 {
                result.status[i] = PixelStatus::Solved;
            }
        }
        let options = MapOptions {
            report_html: false,
            ..MapOptions::default()
        };
        let dir = tempfile::tempdir().unwrap();
        let written = write_maps(&result, dir.path(), &options).unwrap();
        let files = [
            (MapFile::NormalPng, written.normal_png.unwrap()),
            (MapFile::AlbedoPng, written.albedo_png.unwrap()),
            (MapFile::NormalExr, written.normal_exr.unwrap()),
            (MapFile::AlbedoExr, written.albedo_exr.unwrap()),
            (MapFile::Confidence, written.confidence_exr),
        ];
        for (file, path) in files {
            let mut memory = std::io::Cursor::new(Vec::new());
            encode_map_into(&mut memory, &result, file, &path, &options).unwrap();
            let on_disk = std::fs::read(&path).unwrap();
            assert!(
                on_disk.len() > 2 * crate::fsutil::DIRECT_BLOCK,
                "{}",
                file.name()
            );
            assert!(on_disk == memory.into_inner(), "{} differs", file.name());
        }
    }
}
