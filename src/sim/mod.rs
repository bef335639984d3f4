//! The simulated twins of the scanner's real parts (DESIGN.md, "synth, sim"), built on
//! [`crate::synth`]: the camera that renders the synthetic textile lit by whichever LEDs are
//! on, its sibling that photographs the calibration targets, the LED firmware running in its
//! emulator (and the whole emulated capture loop), and the operator who holds the targets in
//! front of the camera. Production modules never import this; the CLI, the bench and the
//! tests wire it in through the production traits ([`crate::capture::camera::Camera`],
//! [`crate::calibration::wizard::TargetSource`], [`crate::calibration::capture::Operator`]).

mod camera;
pub mod emulated;
pub mod emulator;
pub mod operator;
mod target_camera;

pub use camera::{ControllerState, LitSource, SimCamera, SimOutput};
pub use emulated::lit_source;
pub use emulator::{Emulator, EmulatorFiles, PinHistory, PinLog};
pub use target_camera::{Placement, Stage, Target, TargetCamera};
