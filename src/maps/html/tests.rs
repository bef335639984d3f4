use super::*;

#[test]
fn fill_replaces_known_keys_once_and_keeps_unknown_braces() {
    let out = fill("a{{X}}b{{Y}}c{{Z}}", &[("X", "{{Y}}"), ("Y", "2")]);
    assert_eq!(out, "a{{Y}}b2c{{Z}}");
}

#[test]
fn a_damaged_report_and_missing_maps_are_named_on_the_page() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(REPORT_FILE), "{\"rig\": \"x\",").unwrap();
    let (html, summary) = build_page(dir.path());
    let err = summary.report_error.unwrap();
    assert!(err.contains("damaged"), "{err}");
    assert!(html.contains("report.json") && html.contains("damaged"));
    assert!(html.contains("albedo.png") && html.contains("missing"));
    assert!(html.contains("confidence.exr is missing"));
}

/// The page `psscan solve` builds from the maps in memory sees what a rebuild from the files
/// sees (`psscan report`): the same planes up to the PNGs' 16-bit rounding.
#[test]
fn maps_from_memory_equal_the_maps_read_back_from_the_files() {
    use crate::bench::{bench_noise, render_scene, SceneKind};
    use crate::maps::{write_maps, MapOptions};
    use crate::solve::{solve, Estimator, LightSource, SolveInput, SolveOptions};
    let rig = crate::rig::Rig::default_rig();
    let (_, frames) =
        render_scene(&rig, SceneKind::Shadows, 0.02, &crate::progress::Silent).unwrap();
    let input = SolveInput {
        frames: &frames,
        lights: LightSource::Rig(&rig),
        noise: bench_noise(&rig),
        exposure: 1.0,
        mask: None,
    };
    let result = solve(
        &input,
        &SolveOptions::exact(Estimator::Adaptive),
        &crate::progress::Silent,
    )
    .unwrap();
    // A camera-to-display matrix that mixes channels and sends some values out of [0, 1].
    let matrix = [[1.6, -0.4, -0.2], [-0.2, 1.5, -0.3], [0.0, -0.5, 1.5]];
    let options = MapOptions {
        display_matrix: Some(matrix),
        report_html: false,
        ..MapOptions::default()
    };
    let dir = tempfile::tempdir().unwrap();
    write_maps(&result, dir.path(), &options).unwrap();
    let read = FullMaps::read(dir.path(), NormalConvention::OpenGl);
    let memory = FullMaps::from_result(&result, Some(&matrix));
    assert!(read.missing.is_empty(), "{:?}", read.missing);
    assert_eq!((memory.width, memory.height), (read.width, read.height));
    // Borrowed or owned planes alike.
    fn max_diff<A, B>(a: &[A], b: &[B]) -> f32
    where
        A: std::borrow::Borrow<crate::plane::Plane>,
        B: std::borrow::Borrow<crate::plane::Plane>,
    {
        a.iter()
            .zip(b)
            .flat_map(|(p, q)| {
                let (p, q) = (p.borrow(), q.borrow());
                p.data.iter().zip(&q.data).map(|(x, y)| (x - y).abs())
            })
            .fold(0f32, f32::max)
    }
    // Normals: half a 16-bit step of [-1, 1]. Albedo: half a 16-bit step of sRGB, which in
    // linear terms is largest at 1 (slope of the sRGB curve's inverse there: about 2.4).
    let normal = max_diff(
        memory.normal.as_ref().unwrap(),
        read.normal.as_ref().unwrap(),
    );
    assert!(normal <= 1.0 / 65535.0 + 1e-6, "normal {normal}");
    let (memory_albedo, read_albedo) = (memory.albedo.unwrap(), read.albedo.unwrap());
    let albedo = (0..memory.width * memory.height)
        .flat_map(|i| {
            let (m, r) = (memory_albedo.pixel(i), read_albedo.pixel(i));
            (0..3).map(move |c| (m[c] - r[c]).abs())
        })
        .fold(0f32, f32::max);
    assert!(albedo <= 2.5 * 0.5 / 65535.0 + 1e-6, "albedo {albedo}");
    let (memory, read) = (memory.confidence.unwrap(), read.confidence.unwrap());
    assert_eq!((memory.width, memory.height), (read.width, read.height));
    // The classes the solve holds are the numbers the file holds; the float planes, to the bit.
    assert_eq!(memory.status, read.status);
    assert_eq!(memory.fit, read.fit);
    assert!(
        memory.fit.iter().any(|&f| f != 0),
        "the robust fit ran somewhere"
    );
    let floats = max_diff(
        &[memory.predicted_error_deg, memory.residual],
        &[read.predicted_error_deg, read.residual],
    );
    assert_eq!(floats, 0.0);
}

/// A class plane's float value from `confidence.exr` becomes its class number: the whole part
/// of a value in [0, 255), and no class for NaN, negative values and values past a byte's
/// last class (which then count in no legend and take no class's colour).
#[test]
fn class_numbers_of_a_files_floats() {
    use full_maps::{class_of, NO_CLASS};
    for (value, class) in [
        (0.0, 0),
        (-0.0, 0),
        (1.0, 1),
        (5.5, 5),
        (254.9, 254),
        (255.0, NO_CLASS),
        (300.0, NO_CLASS),
        (-1.0, NO_CLASS),
        (f32::NAN, NO_CLASS),
        (f32::INFINITY, NO_CLASS),
        (f32::NEG_INFINITY, NO_CLASS),
    ] {
        assert_eq!(class_of(value), class, "{value}");
    }
}

/// The legend's class counts, counted in parallel blocks, equal a plain count of the file's
/// float values: only whole classes below `n` of non-negative values, the solved pixels only
/// where asked, over more than one block.
#[test]
fn class_counts_count_each_class_below_n_of_the_pixels_asked_for() {
    use crate::plane::Plane;
    let (w, h) = (1000, 150);
    let odd = [f32::NAN, -1.0, 5.5, 300.0, 2.0, 0.0, 1.0, 7.0];
    let status: Vec<f32> = (0..w * h).map(|i| ((i / 7) % 3) as f32).collect();
    let fit: Vec<f32> = (0..w * h).map(|i| odd[i % odd.len()]).collect();
    let numbers = |values: &[f32]| values.iter().map(|&v| full_maps::class_of(v)).collect();
    let zeros = || Plane::new(w, h, 0.0);
    let maps =
        full_maps::FullMaps::of_confidence(numbers(&status), numbers(&fit), [zeros(), zeros()]);
    let conf = maps.confidence.as_ref().unwrap();
    for (values, classes, solved_only, n) in [
        (&status, &conf.status, false, 6),
        (&fit, &conf.fit, true, 3),
        (&fit, &conf.fit, false, 6),
    ] {
        let mut expected = vec![0usize; n];
        for (i, &v) in values.iter().enumerate() {
            if (!solved_only || status[i] == 0.0) && v >= 0.0 && (v as usize) < n {
                expected[v as usize] += 1;
            }
        }
        assert!(expected[..3].iter().all(|&c| c > 0), "the classes occur");
        assert_eq!(class_counts(classes, &maps, solved_only, n), expected);
    }
}
