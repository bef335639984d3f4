//! Calibration of the rig from photographs of targets (DESIGN.md, "calibration"): camera
//! intrinsics and the table's pose (OpenCV, feature `opencv`), the gray chart's white balance
//! and linearity, the white sheet's per-pixel light intensity, and each LED's position fitted
//! to the white sheet; everything written as a bundle that captures and solves cite.

pub mod bundle;
pub mod camera;
pub mod capture;
mod chartfind;
pub mod choice;
mod cv;
pub mod files;
pub mod graychart;
pub mod lights;
pub mod steps;
pub mod table;
pub mod whitesheet;
pub mod wizard;

pub use choice::CalibrationChoice;
