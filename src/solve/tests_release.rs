//! A solve that gives its frames back as it goes against one that keeps them: every output
//! the same bit for bit, on frames large enough that pages are given back mid-solve (had a
//! give-back run ahead of the rows solved, those pixels would read zeros and differ).

use super::tests_fast::assert_same;
use super::*;
use crate::bench::{bench_noise, render_scene, SceneKind};
use crate::progress::Silent;
use crate::rig::Rig;

/// 2 MP: each `f32` plane of a frame spans four 2 MiB pages, so pages are given back while
/// later rows are still being solved.
const MP: f64 = 2.0;

/// The frames' owned bytes (colour planes and saturation flags).
fn owned_bytes(frames: &Frames) -> usize {
    frames
        .lights
        .iter()
        .map(|f| {
            let planes = 3 * f.rgb.r.data.len() * 4;
            planes + f.saturated.as_ref().map_or(0, |m| m.data.len())
        })
        .sum()
}

/// Solves `frames` keeping them, then `copy` (frames of the same values) giving it back (into
/// `previous`'s planes where given); both results and the bytes given back. A clone of
/// `frames` shares their `Arc`s, so planes they share are held outside `copy` and stay whole.
fn kept_and_released(
    rig: &Rig,
    frames: &Frames,
    copy: &mut Frames,
    options: &SolveOptions,
    previous: Option<SolveResult>,
) -> (SolveResult, SolveResult, usize) {
    let input = |frames| SolveInput {
        frames,
        lights: LightSource::Rig(rig),
        noise: bench_noise(rig),
        exposure: 1.0,
        mask: None,
    };
    let kept = solve(&input(frames), options, &Silent).unwrap();
    let mut release = FrameRelease::new(copy);
    // SAFETY: `copy` is lent to nothing but the solve (the caller only reads it afterwards).
    let released =
        unsafe { solve_releasing(&input(copy), options, &Silent, previous, &mut release) }.unwrap();
    (kept, released, release.released_bytes())
}

#[test]
fn giving_the_frames_back_as_the_rows_are_solved_changes_no_output() {
    let rig = Rig::default_rig();
    let (_, frames) = render_scene(&rig, SceneKind::Shadows, MP, &Silent).unwrap();
    let owned = owned_bytes(&frames);
    let kernels = [
        ("default (adaptive, streaming)", SolveOptions::default()),
        ("exact adaptive", SolveOptions::exact(Estimator::Adaptive)),
        (
            "streaming least squares",
            SolveOptions {
                kernel: KernelChoice::new(
                    Estimator::LeastSquares,
                    Method::NormalEquations,
                    Precision::F32,
                    None,
                    true,
                )
                .unwrap(),
                ..SolveOptions::default()
            },
        ),
    ];
    let pixels = frames.width * frames.height;
    for (what, options) in kernels {
        let (kept, released, bytes) =
            kept_and_released(&rig, &frames, &mut frames.clone(), &options, None);
        assert_same(&kept, &released, what);
        if what.contains("adaptive") {
            assert!(kept.escalated > 0, "{what}: the robust fit read frames too");
        }
        // What the outputs fault in, in whole buffers (a plane's `f32`s at most short), less
        // the partial 2 MiB pages at each buffer's ends (two per buffer at most).
        let limit =
            SolveResult::fresh_bytes_touched(pixels, options.predict_error, !options.streaming())
                .min(owned);
        let short = pixels * 4 + frames.lights.len() * 4 * 2 * (2 << 20);
        assert!(
            bytes <= limit && bytes + short >= limit,
            "{what}: gave back {bytes} bytes, the outputs fault in {limit}"
        );
        // Into the last result's planes, the outputs fault nothing in: nothing is given back.
        let (again, reused, bytes) =
            kept_and_released(&rig, &frames, &mut frames.clone(), &options, Some(released));
        assert_same(&again, &reused, what);
        assert_eq!(bytes, 0, "{what}: outputs reused");
    }
}

/// A RAW stack kept as DN, as a DNG set is: besides each frame's DN, the planes the frames
/// share (here the colour ratios, as far as the outputs' fresh bytes reach) are given back as
/// the rows are solved, and every output is still the same bit for bit.
#[test]
fn the_planes_a_raw_stack_shares_are_given_back_too_and_change_no_output() {
    let rig = Rig::default_rig();
    let (_, frames) = render_scene(&rig, SceneKind::Shadows, MP, &Silent).unwrap();
    // Built twice: the copy given back holds `Arc`s of its own.
    let (stack, _) = super::tests_fast::as_cfa_stack(&frames, true);
    let (mut copy, _) = super::tests_fast::as_cfa_stack(&frames, true);
    let options = SolveOptions::default();
    let (kept, released, _) = kept_and_released(&rig, &stack, &mut copy, &options, None);
    assert_same(&kept, &released, "raw stack kept as DN");
    // Given back, whole pages of the shared colour ratios (2 MiB: 524288 `f32`s) read as
    // zeros, beyond the pixels whose ratios are 0 anyway (black in the first frame).
    let zeros = |frames: &Frames| {
        let ratios = &frames.lights[0].cfa.as_ref().unwrap().ratios;
        ratios.r.data.iter().filter(|&&v| v == 0.0).count()
    };
    let (kept_zeros, released_zeros) = (zeros(&stack), zeros(&copy));
    assert!(
        released_zeros >= kept_zeros + (2 << 20) / 4,
        "{released_zeros} ratios read 0 after the release, {kept_zeros} before"
    );
}

#[test]
fn a_solve_that_may_pass_twice_keeps_its_frames() {
    let rig = Rig::default_rig();
    let (_, frames) = render_scene(&rig, SceneKind::Sheen, MP, &Silent).unwrap();
    let mut options = SolveOptions::default();
    options.robust.sheen = Some(SheenModel::default());
    let (kept, released, bytes) =
        kept_and_released(&rig, &frames, &mut frames.clone(), &options, None);
    assert_eq!(bytes, 0, "a second pass reads every frame again");
    assert_same(&kept, &released, "adaptive with sheen");
}
