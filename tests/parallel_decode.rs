//! Loading a capture set decodes its frames in parallel (one frame per core): the developed
//! planes must be bit for bit those of a serial load, for RAW (DNG) and dn16 sets, at full
//! and half resolution.

use psscan::capture::CaptureSet;
use psscan::plane::Frames;
use psscan::progress::Silent;
use psscan::raw::{DevelopOptions, Resolution};
use psscan::rig::Rig;
use psscan::synth::{self, FrameEncoding, SynthSpec};

fn load(set: &CaptureSet, resolution: Resolution, threads: usize) -> Frames {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let options = DevelopOptions {
        resolution,
        subtract_dark: true,
    };
    pool.install(|| set.load_frames_with(&options, &Silent).unwrap().frames)
}

fn bits(frames: &Frames) -> Vec<Vec<u32>> {
    frames
        .lights
        .iter()
        .flat_map(|l| [&l.rgb.r, &l.rgb.g, &l.rgb.b])
        .map(|p| p.data.iter().map(|v| v.to_bits()).collect())
        .collect()
}

#[test]
fn parallel_decode_gives_the_planes_of_a_serial_one() {
    let rig = Rig::default_rig();
    for encoding in [FrameEncoding::Dng, FrameEncoding::Dn16] {
        let dir = tempfile::tempdir().unwrap();
        let spec = SynthSpec {
            width: 96,
            height: 64,
            step: 8.0,
            noise_seed: Some(7),
            encoding,
            ..SynthSpec::demo()
        };
        synth::write_synthetic_set(&rig, &spec, dir.path(), false, &Silent).unwrap();
        let set = CaptureSet::open(dir.path(), None).unwrap();
        let resolutions: &[Resolution] = match encoding {
            FrameEncoding::Dng => &[Resolution::Full, Resolution::Half],
            FrameEncoding::Dn16 => &[Resolution::Full],
        };
        for &resolution in resolutions {
            let serial = load(&set, resolution, 1);
            let parallel = load(&set, resolution, 4);
            assert_eq!(serial.lights.len(), rig.leds.len());
            assert_eq!(
                (serial.width, serial.height),
                (parallel.width, parallel.height)
            );
            assert!(
                bits(&serial) == bits(&parallel),
                "{encoding:?} {resolution:?}: planes differ"
            );
            let masks = |f: &Frames| -> Vec<Option<Vec<bool>>> {
                f.lights
                    .iter()
                    .map(|l| l.saturated.as_ref().map(|m| m.data.clone()))
                    .collect()
            };
            assert_eq!(masks(&serial), masks(&parallel));
        }
    }
}
