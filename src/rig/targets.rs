//! Value types the calibration targets share across layers: the chessboard, the gray chart's
//! layout and its rectangle in an image. The synthetic renderer draws them, the simulated
//! camera photographs them, and calibration measures them.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// A chessboard target: inner corners and square size.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Board {
    /// Inner corners along a row.
    pub cols: usize,
    /// Inner corners along a column.
    pub rows: usize,
    /// Side of one square, metres.
    pub square_m: f64,
}

impl Board {
    /// Parses `9x6` (inner corners) and a square size in millimetres.
    pub fn parse(pattern: &str, square_mm: f64) -> Result<Board> {
        let bad = || {
            Error::Invalid(format!(
                "board `{pattern}`: expected inner corners as COLSxROWS, for example 9x6"
            ))
        };
        let (c, r) = pattern.split_once(['x', 'X']).ok_or_else(bad)?;
        let cols: usize = c.trim().parse().map_err(|_| bad())?;
        let rows: usize = r.trim().parse().map_err(|_| bad())?;
        if cols < 3 || rows < 3 {
            return Err(Error::Invalid(format!(
                "board `{pattern}`: needs at least 3x3 inner corners"
            )));
        }
        if !(square_mm.is_finite() && square_mm > 0.0) {
            return Err(Error::Invalid(format!(
                "square size must be a positive number of millimetres, got {square_mm}"
            )));
        }
        Ok(Board {
            cols,
            rows,
            square_m: square_mm / 1000.0,
        })
    }

    /// Inner corners in the board frame, row by row (x along a row, y down the columns).
    pub fn object_points(&self) -> Vec<[f64; 3]> {
        (0..self.rows)
            .flat_map(|j| {
                (0..self.cols)
                    .map(move |i| [i as f64 * self.square_m, j as f64 * self.square_m, 0.0])
            })
            .collect()
    }

    /// Centre of the inner-corner grid in the board frame.
    pub fn centre(&self) -> [f64; 2] {
        [
            0.5 * (self.cols - 1) as f64 * self.square_m,
            0.5 * (self.rows - 1) as f64 * self.square_m,
        ]
    }
}

/// A chart layout (TOML): `rows x cols` equal patches filling the chart's rectangle, their
/// nominal reflectances row by row, and the central fraction of each patch to sample (edges
/// blur into the neighbours).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChartDescription {
    /// The chart's name, as reports record it.
    pub name: String,
    /// Patch rows.
    pub rows: usize,
    /// Patch columns.
    pub cols: usize,
    /// Nominal diffuse reflectance of each patch (0..1), row by row from the top left.
    pub reflectance: Vec<f64>,
    /// The central fraction of each patch's width and height that is sampled (0..1].
    #[serde(default = "default_sample_fraction")]
    pub sample_fraction: f64,
}

fn default_sample_fraction() -> f64 {
    0.5
}

impl ChartDescription {
    /// Reads and validates a chart layout (TOML) from `path`.
    pub fn load(path: &Path) -> Result<ChartDescription> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let chart: ChartDescription = toml::from_str(&text)
            .map_err(|e| Error::config(path, "chart", e.message().to_string()))?;
        chart
            .validate()
            .map_err(|(field, message)| Error::config(path, field, message))?;
        Ok(chart)
    }

    /// Checks the layout; the error is `(field, reason)`.
    pub fn validate(&self) -> std::result::Result<(), (String, String)> {
        if self.rows == 0 || self.cols == 0 {
            return Err(("rows".into(), "a chart needs at least one patch".into()));
        }
        if self.reflectance.len() != self.rows * self.cols {
            return Err((
                "reflectance".into(),
                format!(
                    "{} values for {} x {} patches",
                    self.reflectance.len(),
                    self.rows,
                    self.cols
                ),
            ));
        }
        if let Some(r) = self
            .reflectance
            .iter()
            .find(|r| !(r.is_finite() && **r > 0.0 && **r <= 1.0))
        {
            return Err((
                "reflectance".into(),
                format!("each must lie in (0, 1], got {r}"),
            ));
        }
        if !(self.sample_fraction > 0.0 && self.sample_fraction <= 1.0) {
            return Err(("sample_fraction".into(), "must lie in (0, 1]".into()));
        }
        Ok(())
    }

    /// Twelve Munsell neutral values, N2 to N9.5, in two rows (reflectances from the Munsell
    /// renotation's luminous reflectance Y).
    pub fn munsell_12() -> ChartDescription {
        ChartDescription {
            name: "munsell-N2-N9.5".into(),
            rows: 2,
            cols: 6,
            reflectance: vec![
                0.0313, 0.0483, 0.0665, 0.0898, 0.1200, 0.1977, 0.2622, 0.3620, 0.4663, 0.5910,
                0.7866, 0.8910,
            ],
            sample_fraction: 0.5,
        }
    }
}

/// The chart's outer rectangle in image pixels (x0, y0) to (x1, y1), as the user marks it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChartRect {
    /// Left edge, image pixels.
    pub x0: f64,
    /// Top edge, image pixels.
    pub y0: f64,
    /// Right edge, image pixels.
    pub x1: f64,
    /// Bottom edge, image pixels.
    pub y1: f64,
}

impl ChartRect {
    /// Parses `X0,Y0,X1,Y1`.
    pub fn parse(text: &str) -> Result<ChartRect> {
        let v: Vec<f64> = text
            .split(',')
            .filter_map(|t| t.trim().parse().ok())
            .collect();
        match v.as_slice() {
            &[x0, y0, x1, y1] if x1 > x0 && y1 > y0 => Ok(ChartRect { x0, y0, x1, y1 }),
            _ => Err(Error::Invalid(format!(
                "chart rectangle `{text}`: expected X0,Y0,X1,Y1 in pixels with X1 > X0 and Y1 > Y0"
            ))),
        }
    }
}
