//! The gray chart on the synthetic rig: white-balance gains from the CFA values against the
//! sensor's known channel response, the linearity fit, and clipped patches flagged.

use psscan::calibration::graychart::{self, Shading};
use psscan::plane::SensorWindow;
use psscan::rig::ChartDescription;
use psscan::rig::Rig;
use psscan::synth::targets;

const WORLD: [f64; 4] = [-0.06, 0.06, -0.025, 0.025];
const VIEW: (usize, usize, f64) = (1024, 512, 2.0);

#[test]
fn white_balance_and_linearity_from_the_cfa_values() {
    let rig = Rig::default_rig();
    let chart = ChartDescription::munsell_12();
    let (mosaics, rect) = targets::gray_chart_mosaics(&rig, &chart, WORLD, VIEW, 1.0, 7);
    let window = SensorWindow::centred(4928, 3264, VIEW.0, VIEW.1, VIEW.2);
    let shading = Shading { rig: &rig, window };
    let report = graychart::calibrate(&mosaics, &chart, &rect, Some(&shading)).unwrap();
    let g = rig.sensor.channel_gain;
    let expected = [g[1] / g[0], 1.0, g[1] / g[2]];
    for (k, light) in report.lights.iter().enumerate() {
        let l = &light.linearity;
        println!(
            "light {k}: white balance {:.4?} (expected {:.4?}), slope {:.4} (LED green power {:.4}), offset {:+.5}, R^2 {:.6}, worst patch {} at {:+.3} %, clipped {:?}",
            light.white_balance, expected, l.slope, rig.led_rgb_power(k)[1], l.offset, l.r_squared, l.worst_patch, l.worst_deviation * 100.0, l.clipped_patches
        );
        // Each patch averages over a thousand samples per channel: gains to 0.5 %.
        for (got, want) in light.white_balance.iter().zip(expected) {
            assert!((got / want - 1.0).abs() < 0.005);
        }
        // Linear sensor, exact shading: slope = the LED's green power, offset ~ 0.
        assert!((l.slope / rig.led_rgb_power(k)[1] - 1.0).abs() < 0.01);
        assert!(l.offset.abs() < 0.002 && l.r_squared > 0.9999);
        assert!(l.clipped_patches.is_empty());
    }

    // Twice the exposure: the brightest patches clip under the overhead LEDs and are flagged
    // and left out of the fits.
    let (bright, rect) = targets::gray_chart_mosaics(&rig, &chart, WORLD, VIEW, 1.8, 8);
    let report = graychart::calibrate(&bright, &chart, &rect, Some(&shading)).unwrap();
    let clipped: Vec<_> = report
        .lights
        .iter()
        .map(|l| l.linearity.clipped_patches.clone())
        .collect();
    println!("exposure 1.8: clipped patches per light {clipped:?}");
    assert!(clipped[6..].iter().all(|c| c.contains(&11)));
    assert!(report.lights.iter().all(|l| l.linearity.r_squared > 0.9999));
}

mod wizard_step {
    use psscan::calibration::wizard::{Step, TargetSource, Wizard};
    use psscan::error::{Error, Result};
    use psscan::plane::{Frames, GrayImage, SensorWindow};
    use psscan::progress::{Progress, Silent};
    use psscan::raw::Mosaic;
    use psscan::rig::Rig;
    use psscan::rig::{Board, ChartDescription};
    use psscan::synth::targets;

    /// The chart on the table of `rig` (here the hand rig is the truth, so the shading model
    /// is exact), at `exposure`, shifted by `shift_m` along x from where the wizard said.
    struct Chart {
        rig: Rig,
        exposure: f64,
        shift_m: f64,
        forgotten: usize,
    }

    impl TargetSource for Chart {
        fn chessboard_view(&mut self, _: usize) -> Result<GrayImage> {
            Err(Error::Invalid("not in this test".into()))
        }
        fn table_view(&mut self) -> Result<GrayImage> {
            Err(Error::Invalid("not in this test".into()))
        }
        fn gray_chart(
            &mut self,
            chart: &ChartDescription,
            world: [f64; 4],
            _: &dyn Progress,
        ) -> Result<(Vec<Mosaic>, SensorWindow)> {
            let [x0, x1, y0, y1] = world;
            let placed = [x0 + self.shift_m, x1 + self.shift_m, y0, y1];
            let (w, h) = targets::binned_size(&self.rig, 4.0);
            let (mosaics, _) = targets::gray_chart_mosaics(
                &self.rig,
                chart,
                placed,
                (w, h, 4.0),
                self.exposure,
                3,
            );
            Ok((mosaics, SensorWindow::centred(4928, 3264, w, h, 4.0)))
        }
        fn white_sheet(&mut self, _: &str, _: usize, _: &dyn Progress) -> Result<Frames> {
            Err(Error::Invalid("not in this test".into()))
        }
        fn view_window(&self) -> SensorWindow {
            SensorWindow::centred(4928, 3264, 1232, 816, 4.0)
        }
        fn forget_gray_chart(&mut self) -> Result<()> {
            self.forgotten += 1;
            Ok(())
        }
    }

    fn verdict(
        exposure: f64,
        shift_m: f64,
    ) -> (psscan::calibration::wizard::ChartVerdict, Step, usize) {
        let tmp = tempfile::tempdir().unwrap();
        let rig = Rig::default_rig();
        let board = Board::parse("9x6", 15.0).unwrap();
        let (mut wiz, _) = Wizard::open(tmp.path(), rig.clone(), "t", board).unwrap();
        wiz.state.step = Step::GrayChart;
        let mut source = Chart {
            rig,
            exposure,
            shift_m,
            forgotten: 0,
        };
        let v = wiz.take_gray_chart(&mut source, &Silent).unwrap();
        (v, wiz.state.step, source.forgotten)
    }

    #[test]
    fn the_wizard_accepts_a_good_chart_and_says_why_it_rejects_a_bad_one() {
        let (good, step, forgotten) = verdict(1.0, 0.0);
        for (k, l) in good.report.lights.iter().enumerate() {
            println!(
                "good chart, LED {k}: worst patch {} at {:+.3} % (allowed {:.3} %)",
                l.linearity.worst_patch,
                100.0 * l.linearity.worst_deviation,
                100.0 * good.linearity_tolerance[k]
            );
        }
        assert!(good.accepted, "{:?}", good.reasons);
        assert_eq!((step, forgotten), (Step::WhiteSheet, 0));
        // Over-exposed: the bright patches clip under the overhead LEDs.
        let (bright, step, forgotten) = verdict(1.8, 0.0);
        println!("over-exposed: {:?}", bright.reasons);
        assert!(!bright.accepted && bright.reasons.iter().any(|r| r.contains("clipped")));
        assert_eq!((step, forgotten), (Step::GrayChart, 1));
        // Laid half a patch (10 mm) off: the samples straddle two patches, the fit bends.
        let (shifted, _, _) = verdict(1.0, 0.01);
        println!("10 mm off: {:?}", shifted.reasons);
        assert!(!shifted.accepted && shifted.reasons.iter().any(|r| r.contains("linear fit")));
    }
}
