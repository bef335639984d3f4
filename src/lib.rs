//! psscan: a photometric-stereo textile scanner.
//!
//! The data's one way through the library (DESIGN.md): a [`rig::Rig`] describes the scanner;
//! [`capture`] produces capture sets on disk (the synthetic rig in [`synth`] produces the same
//! sets with ground truth); [`raw`] decodes frames into linear [`plane::Frames`]; [`solve`]
//! turns frames into a [`solve::SolveResult`]; [`maps`] writes the maps and the report.
//! [`sets`] opens a set of any kind (capture set, DiLiGenT folder, synthetic scene in memory)
//! and solves it through one path, alone or in batches.

#![warn(missing_docs)]
// Pixel and channel loops index several parallel planes at once; an index reads better there
// than zipped iterators.
#![allow(clippy::needless_range_loop)]

pub mod alloc;
pub mod bench;
pub mod calibration;
pub mod capture;
pub mod error;
pub mod eval;
pub mod fsutil;
pub mod io;
pub mod maps;
pub mod math;
pub mod plane;
pub mod progress;
pub mod raw;
pub mod region;
pub mod rig;
pub mod sets;
pub mod sim;
pub mod solve;
pub mod synth;
pub mod timing;

pub use error::{Error, Result};
