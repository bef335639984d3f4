//! The white sheet and the LED fit, without OpenCV: the camera and table are taken as
//! calibrated (the true rig's camera), the LEDs start from hand measurements that are off by
//! 18-30 mm, and the fit must bring every one within 5 mm; the sheet re-solved with the result
//! must come out flat.

use psscan::calibration::{lights, whitesheet};
use psscan::progress::Silent;
use psscan::rig::Rig;
use psscan::solve::NoiseModel;
use psscan::synth::targets;

const STEP: f64 = 8.0;
const REFLECTANCE: f64 = 0.9;

#[test]
fn led_positions_converge_from_hand_measurements_off_by_three_centimetres() {
    let hand = Rig::default_rig();
    let truth = targets::as_built(&hand, 0.03, 5);
    // Camera and table as calibrated; LEDs as measured by hand.
    let mut start = hand.clone();
    start.camera = truth.camera.clone();
    let frames = targets::white_sheet_frames(&truth, STEP, REFLECTANCE, 0.02, 1, 3);
    let sheet = whitesheet::measure(&frames, &start, REFLECTANCE, 8).unwrap();
    let fit = lights::fit(&start, &sheet, &Silent).unwrap();
    for it in &fit.iterations {
        println!(
            "iteration {:2}: max step {:8.3} mm, max power change {:+.2e}, rms residual {:.2e}",
            it.iteration, it.max_step_mm, it.max_power_change, it.rms_relative_residual
        );
    }
    assert!(fit.converged, "the fit converges");
    let mut worst_start: f64 = 0.0;
    let mut best_start = f64::MAX;
    let mut worst: f64 = 0.0;
    for (k, (led, t)) in fit.leds.iter().zip(&truth.leds).enumerate() {
        let start_err = (0..3)
            .map(|i| (led.start_m[i] - t.position_m[i]).powi(2))
            .sum::<f64>()
            .sqrt()
            * 1e3;
        let err = (0..3)
            .map(|i| (led.position_m[i] - t.position_m[i]).powi(2))
            .sum::<f64>()
            .sqrt()
            * 1e3;
        println!("LED {k}: hand measurement off by {start_err:.1} mm, fit off by {err:.2} mm, power {:?} vs {:?}", led.rgb_power, truth.led_rgb_power(k));
        worst_start = worst_start.max(start_err);
        best_start = best_start.min(start_err);
        worst = worst.max(err);
    }
    println!("hand errors {best_start:.1}-{worst_start:.1} mm -> fit within {worst:.2} mm after {} iterations", fit.iterations.len());
    assert!(worst_start > 25.0 && worst_start <= 30.0);
    assert!(worst < 5.0, "every LED within 5 mm, worst {worst:.2} mm");

    // The sheet re-solved with the fitted lights. One exposure first: its noise and the
    // calibration's own (block-mean) error decide how many exposures the check averages.
    let calibrated = fit.apply(&start);
    let noise = NoiseModel::from_sensor(&truth.sensor);
    let single = whitesheet::flatness(&frames, &calibrated, noise, 1, &Silent).unwrap();
    let budget = whitesheet::FLATNESS_TOLERANCE_DEG - single.block_max_deg;
    let n = whitesheet::exposures_needed(single.predicted_noise_max_deg, budget);
    let averaged = targets::white_sheet_frames(&truth, STEP, REFLECTANCE, 0.02, n, 4);
    let check = whitesheet::flatness(&averaged, &calibrated, noise, n, &Silent).unwrap();
    for f in [&single, &check] {
        println!(
            "flatness, {} exposure(s), {} pixels: mean {:.4} deg, max {:.4} deg, 16x16-block max {:.4} deg; predicted noise mean {:.4} deg, 99.9 % max {:.4} deg",
            f.exposures, f.pixels, f.mean_deg, f.max_deg, f.block_max_deg, f.predicted_noise_mean_deg, f.predicted_noise_max_deg
        );
    }
    // The noise model predicts the single exposure's mean error (within 10 %: the rest is
    // the calibration's own error) and its tail.
    assert!((single.mean_deg / single.predicted_noise_mean_deg - 1.0).abs() < 0.1);
    assert!(single.max_deg < single.predicted_noise_max_deg + single.block_max_deg);
    // Every normal of the averaged sheet within 0.5 degrees of straight up.
    assert!(
        check.flat && check.max_deg <= 0.5,
        "max {} deg",
        check.max_deg
    );
}

/// The wizard's last step over a source whose white sheet is photographed under `truth`
/// (the rig as built) while the wizard's calibration holds the hand-measured LEDs.
mod flatness_step {
    use super::{REFLECTANCE, STEP};
    use psscan::calibration::bundle::INDEX_FILE;
    use psscan::calibration::wizard::{Step, TargetSource, Wizard, STATE_FILE};
    use psscan::error::{Error, Result};
    use psscan::plane::{Frames, GrayImage, SensorWindow};
    use psscan::progress::{Progress, Silent};
    use psscan::raw::Mosaic;
    use psscan::rig::{Board, ChartDescription, Rig};
    use psscan::synth::targets;

    struct Sheet {
        truth: Rig,
    }

    impl TargetSource for Sheet {
        fn chessboard_view(&mut self, _: usize) -> Result<GrayImage> {
            Err(Error::Invalid("not in this test".into()))
        }
        fn table_view(&mut self) -> Result<GrayImage> {
            Err(Error::Invalid("not in this test".into()))
        }
        fn gray_chart(
            &mut self,
            _: &ChartDescription,
            _: [f64; 4],
            _: &dyn Progress,
        ) -> Result<(Vec<Mosaic>, SensorWindow)> {
            Err(Error::Invalid("not in this test".into()))
        }
        fn white_sheet(&mut self, _: &str, exposures: usize, _: &dyn Progress) -> Result<Frames> {
            Ok(targets::white_sheet_frames(
                &self.truth,
                STEP,
                REFLECTANCE,
                0.02,
                exposures,
                7,
            ))
        }
        fn view_window(&self) -> SensorWindow {
            let (w, h) = targets::binned_size(&self.truth, STEP);
            SensorWindow::centred(
                self.truth.camera.width as usize,
                self.truth.camera.height as usize,
                w,
                h,
                STEP,
            )
        }
    }

    /// The wizard at its flatness step with the hand rig as its calibration, over a sheet
    /// photographed under `truth`: what `finish` returned, and the folder.
    fn finish(truth: Rig) -> (Result<()>, Wizard, tempfile::TempDir) {
        let tmp = tempfile::tempdir().unwrap();
        let mut hand = Rig::default_rig();
        hand.camera = truth.camera.clone();
        let board = Board::parse("9x6", 15.0).unwrap();
        let (mut wiz, _) = Wizard::open(tmp.path(), hand, "t", board).unwrap();
        wiz.state.step = Step::Flatness;
        wiz.state.calibration.sheet_reflectance = Some(REFLECTANCE);
        let outcome = wiz.finish(&mut Sheet { truth }, &Silent).map(|_| ());
        (outcome, wiz, tmp)
    }

    /// LEDs 3 cm from where the calibration puts them tilt the re-solved sheet by degrees: the
    /// check fails, the error says so and that no bundle was written, no bundle index exists,
    /// and the saved state records the failed check and sends the session back to the white
    /// sheet.
    #[test]
    fn a_sheet_that_is_not_flat_writes_no_bundle_and_sends_the_wizard_back() {
        let truth = targets::as_built(&Rig::default_rig(), 0.03, 5);
        let (outcome, wiz, tmp) = finish(truth);
        let message = outcome
            .expect_err("a non-flat sheet fails the step")
            .to_string();
        println!("{message}");
        assert!(
            message.contains("flatness check failed") && message.contains("no bundle was written"),
            "{message}"
        );
        assert!(!tmp.path().join(INDEX_FILE).exists(), "no bundle index");
        let state = std::fs::read_to_string(tmp.path().join(STATE_FILE)).unwrap();
        assert!(state.contains("step = \"white-sheet\""), "{state}");
        let check = wiz.state.calibration.flatness.as_ref().unwrap();
        assert!(!check.flat && check.max_deg > 1.0, "{}", check.max_deg);
        assert!(message.contains(&format!("{:.3} deg", check.max_deg)));
    }

    /// The control: the sheet photographed under the rig the calibration holds comes out flat
    /// and the bundle is written.
    #[test]
    fn a_flat_sheet_writes_the_bundle() {
        let mut truth = Rig::default_rig();
        truth.camera = Rig::default_rig().camera;
        let (outcome, wiz, tmp) = finish(truth);
        outcome.expect("a flat sheet finishes the wizard");
        assert!(tmp.path().join(INDEX_FILE).exists());
        assert_eq!(wiz.state.step, Step::Done);
        assert!(wiz.state.calibration.flatness.as_ref().unwrap().flat);
    }
}

/// Resuming a wizard session with another name, board or rig would mix two sessions'
/// photographs: it is refused with the values to resume with; the same values resume it.
#[test]
fn a_wizard_session_resumes_only_with_its_own_rig_name_and_board() {
    use psscan::calibration::wizard::Wizard;
    use psscan::rig::Board;
    let tmp = tempfile::tempdir().unwrap();
    let rig = Rig::default_rig();
    let board = Board::parse("9x6", 15.0).unwrap();
    let (_, resumed) = Wizard::open(tmp.path(), rig.clone(), "studio-a", board).unwrap();
    assert!(!resumed);
    let mut other_rig = rig.clone();
    other_rig.name = "other-rig".into();
    let other_board = Board::parse("7x5", 20.0).unwrap();
    for (r, name, b) in [
        (&rig, "wizard", board),
        (&rig, "studio-a", other_board),
        (&other_rig, "studio-a", board),
    ] {
        let message = Wizard::open(tmp.path(), r.clone(), name, b)
            .err()
            .expect("another session's values are refused")
            .to_string();
        assert!(
            message.contains(&format!("rig `{}`", rig.name))
                && message.contains("--name studio-a")
                && message.contains("--wizard-board 9x6")
                && message.contains("--wizard-square-mm 15`"),
            "{message}"
        );
    }
    let (wiz, resumed) = Wizard::open(tmp.path(), rig, "studio-a", board).unwrap();
    assert!(resumed && wiz.state.name == "studio-a");
}
