//! The gray chart on the synthetic rig: white-balance gains from the CFA values against the
//! sensor's known channel response, the linearity fit, and clipped patches flagged.

use psscan::calibration::graychart::{self, ChartDescription, Shading};
use psscan::plane::SensorWindow;
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
