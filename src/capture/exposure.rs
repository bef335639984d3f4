//! The capture primitives every photograph through the LED controller shares, written once:
//! preparing the controller for a session, switching an LED and confirming it with `STATE`,
//! and the settle-fire-confirm of one exposure under the keepalive. The sequencer's frames,
//! the single shots of the calibration wizard and its capture source all use them.

use std::path::Path;
use std::time::Duration;

use super::camera::{Camera, Shot};
use super::interrupt::Interrupt;
use super::lights::{describe_on, FirmwareInfo, Keepalive, LightState, SharedLights};
use crate::error::{Error, Result};

/// Identifies the controller, checks that it drives all `leds` LEDs of the rig, sets its
/// keepalive timeout when asked, and switches every LED off. Returns what the firmware said
/// and the timeout it now runs with (milliseconds).
pub fn prepare_controller(
    lights: &SharedLights,
    leds: usize,
    timeout_ms: Option<u32>,
) -> Result<(FirmwareInfo, u32)> {
    let mut l = lights.lock();
    let firmware = l.identify()?;
    if leds > firmware.leds {
        return Err(Error::device(
            l.name(),
            format!(
                "the rig has {leds} LEDs but the controller drives only {}",
                firmware.leds
            ),
        ));
    }
    if let Some(ms) = timeout_ms {
        l.set_timeout(ms)?;
    }
    l.off()?;
    let timeout_ms = l.state()?.timeout_ms;
    Ok((firmware, timeout_ms))
}

/// Switches LED `led` on (`None`: all off) and confirms it with `STATE`; returns that state.
pub fn switch_and_confirm(lights: &SharedLights, led: Option<usize>) -> Result<LightState> {
    let mut l = lights.lock();
    match led {
        Some(k) => l.on(k)?,
        None => l.off()?,
    }
    let state = l.state()?;
    confirm(&l.name(), led, &state, "before the shot")?;
    Ok(state)
}

/// With `led` switched on and confirmed: settles for `settle` under the keepalive, fires the
/// camera into `dest` with the keepalive covering the shot, and confirms that the controller
/// still reports `led` (for a lit shot, `tripped=0` proves the LED stayed on throughout).
pub fn settle_fire_confirm(
    lights: &SharedLights,
    keepalive: &Keepalive,
    camera: &mut dyn Camera,
    led: Option<usize>,
    dest: &Path,
    settle: Duration,
    interrupt: &Interrupt,
) -> Result<Shot> {
    {
        let _lease = keepalive.lease(settle + Duration::from_secs(1));
        if !interrupt.sleep(settle) {
            interrupt.check()?;
        }
    }
    let shot = {
        let _lease = keepalive.lease(camera.max_shot_time());
        camera.capture(dest, interrupt)?
    };
    // Ctrl-C during the shot: the keepalive may have switched the LED off mid-exposure, so
    // the shot is not kept.
    interrupt.check()?;
    let mut l = lights.lock();
    let state = l.state()?;
    confirm(&l.name(), led, &state, "after the shot")?;
    Ok(shot)
}

/// The controller must report `led` (and, for a lit shot, `tripped=0`: the LED stayed on).
fn confirm(device: &str, led: Option<usize>, state: &LightState, when: &str) -> Result<()> {
    if state.on == led && !(led.is_some() && state.tripped) {
        return Ok(());
    }
    let why = if state.tripped {
        format!(
            " (tripped=1: the firmware switched the LED off by itself after {} ms without a \
             word from the host; the host or camera stalled)",
            state.timeout_ms
        )
    } else {
        String::new()
    };
    Err(Error::device(
        device,
        format!(
            "{when}: reports {}, expected {}{why}",
            describe_on(state.on),
            describe_on(led)
        ),
    ))
}
