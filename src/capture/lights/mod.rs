//! The LED controller: a trait the sequencer drives, the serial implementation that talks to
//! the Arduino firmware (`firmware/`, protocol in `firmware/PROTOCOL.md`), an in-process mock
//! for unit tests, port discovery, and the keepalive that holds the firmware's host-silence
//! timeout off during long shots without defeating it when the host hangs.
//!
//! Layers, as in espflash: `protocol` (pure line formats) < `serial` (a port, timeouts,
//! retries, handshake) < `LightController` (what a capture needs) < `keepalive` (a thread that
//! shares the controller with the sequencer).

pub mod keepalive;
pub mod mock;
pub mod ports;
pub mod protocol;
pub mod selftest;
pub mod serial;

use std::sync::{Arc, Mutex, MutexGuard};

pub use keepalive::{Keepalive, Lease};
pub use mock::{MockFault, MockLights, MockProbe};
pub use ports::{list_ports, resolve_port, PortInfo};
pub use protocol::{FirmwareInfo, LightState};
pub use selftest::{test_leds, LedCheck, LedTest};
pub use serial::{LineNoise, SerialLights, SerialOptions};

use crate::error::Result;

/// What a capture session needs from the LED controller. Every call is one request and one
/// answer; implementations switch all LEDs off when dropped.
pub trait LightController: Send {
    /// Names the device for messages, e.g. `LED controller on /dev/ttyACM0`.
    fn name(&self) -> String;
    /// Asks the controller who it is and checks that this host can drive it.
    fn identify(&mut self) -> Result<FirmwareInfo>;
    /// LED `led` on, every other LED off.
    fn on(&mut self, led: usize) -> Result<()>;
    /// All LEDs off.
    fn off(&mut self) -> Result<()>;
    /// The controller's own account of its LEDs.
    fn state(&mut self) -> Result<LightState>;
    /// Sets the host-silence timeout after which the controller switches the LEDs off by
    /// itself.
    fn set_timeout(&mut self, ms: u32) -> Result<()>;
    /// Tells the controller the host is alive (restarts its silence clock).
    fn keepalive(&mut self) -> Result<()>;
}

/// A controller shared between the sequencer and the keepalive thread.
#[derive(Clone)]
pub struct SharedLights(Arc<Mutex<Box<dyn LightController>>>);

impl SharedLights {
    /// Wraps `controller` for sharing; clones of the result drive the same controller.
    pub fn new(controller: Box<dyn LightController>) -> Self {
        SharedLights(Arc::new(Mutex::new(controller)))
    }

    /// Exclusive use for one or a few requests. A panic while holding the lock does not make
    /// the controller unusable: switching the LEDs off must still work afterwards.
    pub fn lock(&self) -> MutexGuard<'_, Box<dyn LightController>> {
        self.0
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// Switches the LEDs off, returning a sentence for the operator on what was left behind.
    pub fn off_and_report(&self) -> String {
        let mut lights = self.lock();
        match lights.off() {
            Ok(()) => "all LEDs are off".into(),
            Err(e) => format!(
                "could not switch the LEDs off ({e}); the firmware switches them off by itself \
                 when the host has been silent longer than its timeout"
            ),
        }
    }
}

/// A controller's `on` state in words: `LED k on` or `all LEDs off`.
pub fn describe_on(on: Option<usize>) -> String {
    match on {
        Some(k) => format!("LED {k} on"),
        None => "all LEDs off".into(),
    }
}
