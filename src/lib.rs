//! psscan: a photometric-stereo textile scanner.
//!
//! The data's one way through the library (DESIGN.md): a [`rig::Rig`] describes the scanner;
//! [`capture`] produces capture sets on disk (the synthetic rig in [`synth`] produces the same
//! sets with ground truth); [`raw`] decodes frames into linear [`plane::Frames`]; [`solve`]
//! turns frames into a [`solve::SolveResult`]; [`maps`] writes the maps and the report.
//! [`sets`] opens a set of any kind (capture set, DiLiGenT folder, synthetic scene in memory)
//! and solves it through one path, alone or in batches.

// Pixel and channel loops index several parallel planes at once; an index reads better there
// than zipped iterators.
#![allow(clippy::needless_range_loop)]

// Every public item documented: on for the layers finished so far (0 to 2 of DESIGN.md),
// module by module upward; crate-wide once every module is done.

#[warn(missing_docs)]
pub mod alloc;
#[warn(missing_docs)]
pub mod bench;
#[warn(missing_docs)]
pub mod calibration;
#[warn(missing_docs)]
pub mod capture;
#[warn(missing_docs)]
pub mod error;
pub mod eval;
#[warn(missing_docs)]
pub mod fsutil;
#[warn(missing_docs)]
pub mod io;
pub mod maps;
#[warn(missing_docs)]
pub mod math;
#[warn(missing_docs)]
pub mod plane;
#[warn(missing_docs)]
pub mod progress;
pub mod raw;
#[warn(missing_docs)]
pub mod region;
#[warn(missing_docs)]
pub mod rig;
#[warn(missing_docs)]
pub mod sets;
#[warn(missing_docs)]
pub mod sim;
pub mod solve;
#[warn(missing_docs)]
pub mod synth;
#[warn(missing_docs)]
pub mod timing;

pub use error::{Error, Result};
