//! An in-process LED controller for unit tests: the firmware's rules (one LED at a time,
//! silence timeout with the tripped flag) in a few lines, a probe to see which LED is on, a
//! log of every request, and faults on demand. Not a stand-in for the real firmware: the
//! emulator tests (firmware in simavr behind a pty) cover that.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::protocol::{FirmwareInfo, LightState, FIRMWARE_NAME, PROTOCOL_VERSION};
use super::LightController;
use crate::error::{Error, LinkError, Result};

/// A fault the mock plays when it sees a request (by its protocol line, e.g. `ON 3`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum MockFault {
    /// From this request on, the controller is gone (as when the cable is pulled).
    VanishAt(String),
    /// This request is refused with `ERR <code>`.
    Refuse(String, u32),
}

struct MockState {
    on: Option<usize>,
    timeout: Duration,
    tripped: bool,
    last_contact: Instant,
    gone: bool,
    faults: Vec<MockFault>,
    log: Vec<String>,
}

impl MockState {
    /// The firmware's silence rule, applied lazily whenever someone looks.
    fn apply_silence(&mut self) {
        if self.on.is_some() && self.last_contact.elapsed() > self.timeout {
            self.on = None;
            self.tripped = true;
        }
    }
}

/// The mock controller.
pub struct MockLights {
    leds: usize,
    shared: Arc<Mutex<MockState>>,
}

/// A view of a mock's LEDs from outside (the simulated camera, tests).
#[derive(Clone)]
pub struct MockProbe(Arc<Mutex<MockState>>);

impl MockLights {
    /// A mock with `leds` LED channels, all off, a 3 s silence timeout and no faults planned.
    pub fn new(leds: usize) -> MockLights {
        MockLights {
            leds,
            shared: Arc::new(Mutex::new(MockState {
                on: None,
                timeout: Duration::from_millis(3000),
                tripped: false,
                last_contact: Instant::now(),
                gone: false,
                faults: Vec::new(),
                log: Vec::new(),
            })),
        }
    }

    /// The mock with `fault` added to its plan, played when the request it names arrives.
    pub fn with_fault(self, fault: MockFault) -> MockLights {
        lock(&self.shared).faults.push(fault);
        self
    }

    /// A handle that sees this mock's LEDs and request log from outside, even after the mock itself
    /// has been moved into a [`super::SharedLights`].
    pub fn probe(&self) -> MockProbe {
        MockProbe(self.shared.clone())
    }

    /// One request: checks faults, logs it, applies the silence rule, then `action`.
    fn request<T>(
        &mut self,
        line: String,
        action: impl FnOnce(&mut MockState) -> Result<T>,
    ) -> Result<T> {
        let mut state = lock(&self.shared);
        let vanish = MockFault::VanishAt(line.clone());
        if state.faults.contains(&vanish) {
            state.gone = true;
        }
        if state.gone {
            return Err(Error::Link {
                device: "mock LED controller".into(),
                source: LinkError::Vanished {
                    what: format!("\"{line}\""),
                    source: std::io::Error::new(
                        std::io::ErrorKind::BrokenPipe,
                        "the mock's fault plan",
                    ),
                },
            });
        }
        state.apply_silence();
        state.log.push(line.clone());
        let refusal = state.faults.iter().find_map(|f| match f {
            MockFault::Refuse(l, code) if *l == line => Some(*code),
            _ => None,
        });
        if let Some(code) = refusal {
            return Err(refused(&line, code, "(the mock's fault plan)"));
        }
        state.last_contact = Instant::now();
        action(&mut state)
    }
}

/// The mock's `ERR` answer to `line`, as the serial link reports one.
fn refused(line: &str, code: u32, reason: &str) -> Error {
    Error::Link {
        device: "mock LED controller".into(),
        source: LinkError::Refused {
            what: format!("\"{line}\""),
            code,
            reason: reason.into(),
        },
    }
}

fn lock(shared: &Arc<Mutex<MockState>>) -> MutexGuard<'_, MockState> {
    shared.lock().unwrap_or_else(|p| p.into_inner())
}

impl MockProbe {
    /// The LEDs that are on now.
    pub fn lit(&self) -> Vec<usize> {
        let mut state = lock(&self.0);
        state.apply_silence();
        state.on.into_iter().collect()
    }

    /// Every request the mock received, as protocol lines.
    pub fn log(&self) -> Vec<String> {
        lock(&self.0).log.clone()
    }
}

impl LightController for MockLights {
    fn name(&self) -> String {
        "mock LED controller".into()
    }

    fn identify(&mut self) -> Result<FirmwareInfo> {
        let leds = self.leds;
        self.request("ID".into(), |_| {
            Ok(FirmwareInfo {
                name: FIRMWARE_NAME.into(),
                firmware_version: "mock".into(),
                protocol: PROTOCOL_VERSION,
                leds,
            })
        })
    }

    fn on(&mut self, led: usize) -> Result<()> {
        let leds = self.leds;
        self.request(format!("ON {led}"), |s| {
            if led >= leds {
                return Err(refused(&format!("ON {led}"), 4, "out of range"));
            }
            s.on = Some(led);
            s.tripped = false;
            Ok(())
        })
    }

    fn off(&mut self) -> Result<()> {
        self.request("OFF".into(), |s| {
            s.on = None;
            Ok(())
        })
    }

    fn state(&mut self) -> Result<LightState> {
        self.request("STATE".into(), |s| {
            Ok(LightState {
                on: s.on,
                timeout_ms: s.timeout.as_millis() as u32,
                tripped: s.tripped,
            })
        })
    }

    fn set_timeout(&mut self, ms: u32) -> Result<()> {
        self.request(format!("TIMEOUT {ms}"), |s| {
            s.timeout = Duration::from_millis(ms as u64);
            Ok(())
        })
    }

    fn keepalive(&mut self) -> Result<()> {
        self.request("PING".into(), |_| Ok(()))
    }
}

impl Drop for MockLights {
    fn drop(&mut self) {
        let mut state = lock(&self.shared);
        if !state.gone {
            state.on = None;
            state.log.push("OFF (drop)".into());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_led_at_a_time_and_off_on_drop() {
        let mut lights = MockLights::new(10);
        let probe = lights.probe();
        lights.on(3).unwrap();
        lights.on(5).unwrap();
        assert_eq!(probe.lit(), vec![5]);
        assert!(lights.on(10).is_err());
        drop(lights);
        assert!(probe.lit().is_empty());
        assert_eq!(probe.log().last().unwrap(), "OFF (drop)");
    }

    #[test]
    fn silence_switches_off_and_trips() {
        let mut lights = MockLights::new(10);
        lights.set_timeout(100).unwrap();
        lights.on(2).unwrap();
        std::thread::sleep(Duration::from_millis(150));
        let state = lights.state().unwrap();
        assert_eq!(state.on, None);
        assert!(state.tripped);
    }

    #[test]
    fn faults_play_as_asked() {
        let mut lights = MockLights::new(10)
            .with_fault(MockFault::Refuse("ON 1".into(), 4))
            .with_fault(MockFault::VanishAt("ON 2".into()));
        assert!(lights.on(1).unwrap_err().to_string().contains("ERR 4"));
        assert!(lights.on(2).unwrap_err().to_string().contains("vanished"));
        assert!(lights.off().is_err());
    }
}
