//! One photograph outside a capture set (the calibration wizard's chessboard views): the same
//! care as the sequencer's frames — switch the LED, confirm it with `STATE`, settle, fire with
//! the keepalive covering the shot, confirm again — and all LEDs off when it returns, whatever
//! happened (error, Ctrl-C).

use std::path::Path;
use std::time::Duration;

use super::camera::{Camera, Shot};
use super::exposure::{settle_fire_confirm, switch_and_confirm};
use super::interrupt::Interrupt;
use super::lights::{Keepalive, SharedLights};
use crate::error::{Error, Result};

/// Takes one photograph into `dest` with LED `led` on (`None`: all off). The LEDs are off
/// afterwards; an error says so (or why not).
pub fn shoot_one(
    lights: &SharedLights,
    camera: &mut dyn Camera,
    led: Option<usize>,
    dest: &Path,
    settle: Duration,
    interrupt: &Interrupt,
) -> Result<Shot> {
    let shot = lit_shot(lights, camera, led, dest, settle, interrupt);
    let off = lights.lock().off();
    match (shot, off) {
        (Ok(shot), Ok(())) => Ok(shot),
        (Ok(_), Err(e)) => Err(e),
        (Err(e), _) => {
            let _ = std::fs::remove_file(dest);
            let leds = lights.off_and_report();
            Err(match e {
                Error::Interrupted(m) => Error::Interrupted(format!("{m}; {leds}")),
                e @ (Error::Device { .. } | Error::Link { .. }) => e.with_aftermath(leds),
                other => other,
            })
        }
    }
}

fn lit_shot(
    lights: &SharedLights,
    camera: &mut dyn Camera,
    led: Option<usize>,
    dest: &Path,
    settle: Duration,
    interrupt: &Interrupt,
) -> Result<Shot> {
    interrupt.check()?;
    let timeout_ms = switch_and_confirm(lights, led)?.timeout_ms;
    let keepalive = Keepalive::start(
        lights.clone(),
        Duration::from_millis(timeout_ms as u64 / 3),
        interrupt.clone(),
    );
    settle_fire_confirm(lights, &keepalive, camera, led, dest, settle, interrupt)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::lights::{MockFault, MockLights};
    use crate::rig::Rig;
    use crate::sim::{Placement, Stage, Target, TargetCamera};
    use crate::synth::targets::Chessboard;

    fn camera(probe: crate::capture::lights::MockProbe) -> (TargetCamera, Stage) {
        let stage = Stage::default();
        stage.place(Placement {
            target: Target::Table,
            step: 128.0,
            ..Placement::default()
        });
        let chess = Chessboard {
            board: crate::rig::Board::parse("9x6", 15.0).unwrap(),
            border_squares: 1.0,
        };
        let cam = TargetCamera::new(Rig::default_rig(), chess, stage.clone(), Box::new(probe), 1);
        (cam, stage)
    }

    #[test]
    fn one_shot_lights_one_led_and_leaves_all_off() {
        let mock = MockLights::new(10);
        let probe = mock.probe();
        let lights = SharedLights::new(Box::new(mock));
        let (mut cam, _stage) = camera(probe.clone());
        let dir = tempfile::tempdir().unwrap();
        let dest = dir.path().join("v.png");
        let shot = shoot_one(
            &lights,
            &mut cam,
            Some(6),
            &dest,
            Duration::from_millis(1),
            &Interrupt::new(),
        )
        .unwrap();
        assert_eq!(shot.lit, Some(vec![6]));
        assert!(dest.is_file() && probe.lit().is_empty());
        let log = probe.log();
        let on = log.iter().position(|l| l == "ON 6").unwrap();
        assert_eq!(&log[on..], ["ON 6", "STATE", "STATE", "OFF"]);

        // Ctrl-C before the shot: no file, all off, and the error says so.
        let stop = Interrupt::new();
        stop.set();
        let err = shoot_one(&lights, &mut cam, Some(6), &dest, Duration::ZERO, &stop).unwrap_err();
        assert!(matches!(err, Error::Interrupted(_)));
        assert!(err.to_string().contains("all LEDs are off"), "{err}");
        assert!(probe.lit().is_empty());
    }

    #[test]
    fn a_controller_that_refuses_stops_the_shot_with_the_leds_off() {
        let mock = MockLights::new(10).with_fault(MockFault::Refuse("ON 6".into(), 4));
        let probe = mock.probe();
        let lights = SharedLights::new(Box::new(mock));
        let (mut cam, _stage) = camera(probe.clone());
        let dir = tempfile::tempdir().unwrap();
        let err = shoot_one(
            &lights,
            &mut cam,
            Some(6),
            &dir.path().join("v.png"),
            Duration::ZERO,
            &Interrupt::new(),
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("ERR 4") && err.contains("all LEDs are off"),
            "{err}"
        );
        assert!(probe.lit().is_empty());
    }
}
