//! The LED self-test (`psscan lights test`): each LED the controller drives switched on in
//! turn and confirmed with `STATE`, then all off.

use std::time::Duration;

use serde::Serialize;

use super::{describe_on, SharedLights};
use crate::capture::interrupt::Interrupt;
use crate::error::Result;

/// One LED's check: whether the controller reported it (and only it) on, untripped.
#[derive(Clone, Debug, Serialize)]
pub struct LedCheck {
    /// The LED switched on.
    pub led: usize,
    /// The controller reported exactly this LED on, not tripped.
    pub ok: bool,
    /// What the controller reported, in words.
    pub state: String,
}

/// What the self-test found.
#[derive(Clone, Debug)]
pub struct LedTest {
    /// One check per LED tested, in order.
    pub checks: Vec<LedCheck>,
    /// The interrupt stopped the test before every LED was tested.
    pub interrupted: bool,
}

/// Switches each LED the controller drives on in turn, confirms it with `STATE`, and leaves it
/// on for `dwell` (for a person to look); `each` sees every check as it is made. All LEDs are
/// off when it returns without error.
pub fn test_leds(
    lights: &SharedLights,
    dwell: Duration,
    interrupt: &Interrupt,
    each: &mut dyn FnMut(&LedCheck),
) -> Result<LedTest> {
    let leds = lights.lock().identify()?.leds;
    let mut checks = Vec::new();
    for led in 0..leds {
        let state = {
            let mut l = lights.lock();
            l.on(led)?;
            l.state()?
        };
        let check = LedCheck {
            led,
            ok: state.on == Some(led) && !state.tripped,
            state: describe_on(state.on),
        };
        each(&check);
        checks.push(check);
        if !interrupt.sleep(dwell) {
            break;
        }
    }
    lights.lock().off()?;
    Ok(LedTest {
        checks,
        interrupted: interrupt.is_set(),
    })
}
