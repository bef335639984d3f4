//! The page's figures that only the maps decide, built before the report exists.

use std::path::{Path, PathBuf};

use super::full_maps::FullMaps;
use super::images::Reduction;
use super::relight::RelightTextures;
use super::{class_parts, derived, map_parts, textures};
use crate::solve::SolveResult;

/// The page's figures that only the maps decide: the relight's textures, the maps at display
/// size (with a derive's height and roughness) and the per-pixel class figures. They need no
/// report, so `psscan solve` builds them while it writes the map files, whose waits for the
/// disk leave the cores idle; the rest of the page embeds the report, written after them.
pub struct MapFigures<'a> {
    pub(super) maps: FullMaps<'a>,
    pub(super) reduction: Reduction,
    pub(super) derived: Option<PathBuf>,
    pub(super) textures: Option<RelightTextures>,
    pub(super) map_html: String,
    pub(super) derived_maps: Vec<String>,
    pub(super) classes: String,
}

impl<'a> MapFigures<'a> {
    /// The figures of a solve whose maps are still in memory, with the derive in `dir`
    /// (the solve's folder) when it holds one already.
    pub fn of_solve(
        dir: &Path,
        result: &'a SolveResult,
        display_matrix: Option<&[[f64; 3]; 3]>,
    ) -> Self {
        let maps = FullMaps::from_result(result, display_matrix);
        Self::build(maps, derived::locate(dir, None))
    }

    pub(super) fn build(maps: FullMaps<'a>, derived: Option<PathBuf>) -> Self {
        let reduction = Reduction::for_size(maps.width, maps.height);
        // The display-size figures are independent of each other: built side by side.
        let ((textures, (map_html, derived_maps)), classes) = rayon::join(
            || {
                let textures = textures::relight_textures(&maps, &reduction);
                let map_html = map_parts(&maps, textures.as_ref(), derived.as_deref());
                (textures, map_html)
            },
            || class_parts(&maps, &reduction),
        );
        MapFigures {
            maps,
            reduction,
            derived,
            textures,
            map_html,
            derived_maps,
            classes,
        }
    }
}
