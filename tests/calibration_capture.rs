//! The wizard's capture source on the in-process mock controller: the simulated camera sees
//! the chessboard only when the LED the controller switched on is the one it reads, so the
//! views depend on the controller's state, not on a side channel.
#![cfg(feature = "opencv")]

use std::time::Duration;

use psscan::calibration::capture::Captured;
use psscan::calibration::wizard::Wizard;
use psscan::capture::lights::{MockLights, SharedLights};
use psscan::capture::Interrupt;
use psscan::rig::Board;
use psscan::rig::Rig;
use psscan::sim::operator::simulated_camera;
use psscan::sim::LitSource;

#[test]
fn opencv_capture_source_views_are_lit_by_what_the_controller_has_on() {
    let hand = Rig::default_rig();
    let board = Board::parse("9x6", 15.0).unwrap();
    for camera_reads_the_controller in [true, false] {
        let tmp = tempfile::tempdir().unwrap();
        let mock = MockLights::new(10);
        let probe = mock.probe();
        // A second controller nobody switches: a camera reading it sees every LED off.
        let elsewhere = MockLights::new(10);
        let lit: Box<dyn LitSource> = if camera_reads_the_controller {
            Box::new(probe.clone())
        } else {
            Box::new(elsewhere.probe())
        };
        let (camera, scene) = simulated_camera(&hand, board, 5, lit);
        let mut source = Captured::open(
            tmp.path(),
            &hand,
            SharedLights::new(Box::new(mock)),
            Box::new(camera),
            Some(Box::new(scene)),
            Duration::from_millis(1),
            Interrupt::new(),
        )
        .unwrap();
        let (mut wiz, _) = Wizard::open(tmp.path(), hand.clone(), "t", board).unwrap();
        let v = wiz.take_view(&mut source).unwrap();
        println!(
            "camera reads the controller: {camera_reads_the_controller}: {} {}",
            v.accepted, v.reason
        );
        assert_eq!(v.accepted, camera_reads_the_controller, "{}", v.reason);
        // LED 6 (nearest the camera axis) was switched on for the shot, and off after it.
        let log = probe.log();
        assert!(log.iter().any(|l| l == "ON 6"), "{log:?}");
        assert!(probe.lit().is_empty());
    }
}
