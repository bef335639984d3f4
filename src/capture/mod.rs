//! Capture sets: the manifest and the on-disk set (written frame by frame, read back with
//! every check). The LED controller, cameras and the sequencer join this module with the
//! capture work (issue "Capture").

pub mod diligent;
pub mod manifest;
pub mod set;

pub use diligent::DiligentSet;
pub use manifest::{CameraSettings, FrameEntry, FrameKind, ImageInfo, Manifest, SyntheticInfo};
pub use set::{light_file_name, CaptureSet, CaptureSetWriter, LoadedFrames};
