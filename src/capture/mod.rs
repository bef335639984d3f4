//! Capture: the LED controller (serial protocol to the Arduino firmware, a mock, port
//! discovery, keepalive), cameras (libgphoto2, external command), the sequencer that shoots a
//! set frame by frame, and capture sets on disk (manifest, atomic frame writes, checked
//! reading, resume). The simulated camera and the firmware emulator are the `sim` module's.

pub mod camera;
pub mod diligent;
pub mod exposure;
mod frame_check;
pub mod interrupt;
mod led_shading;
pub mod lights;
pub mod manifest;
mod sequencer;
mod set;
mod single;

pub use diligent::DiligentSet;
pub use interrupt::Interrupt;
pub use manifest::{CameraSettings, FrameEntry, FrameKind, ImageInfo, Manifest, SyntheticInfo};
pub use sequencer::{run_capture, CaptureOptions, CaptureReport, FrameRecord, FrameStatus};
pub use set::{light_file_name, CaptureSet, CaptureSetWriter, DroppedFrame, LoadedFrames};
pub use single::shoot_one;
