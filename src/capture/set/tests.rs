use super::*;
use crate::plane::SensorWindow;
use crate::progress::Silent;
use crate::raw::{encode_png16, DnImage, Levels};

fn rig3() -> Rig {
    let mut rig = Rig::default_rig();
    rig.leds.truncate(3);
    rig
}

fn image_info() -> ImageInfo {
    ImageInfo {
        width: 2,
        height: 2,
        window: SensorWindow::FULL,
        levels: Levels {
            black: 600.0,
            white: 15600.0,
        },
        exposure: 1.0,
        encoding: "dn16".into(),
    }
}

fn frame_bytes(value: u16) -> Vec<u8> {
    encode_png16(&DnImage {
        width: 2,
        height: 2,
        data: vec![value; 12],
    })
    .unwrap()
}

fn write_set(dir: &Path, lights: usize) -> CaptureSetWriter {
    let mut w =
        CaptureSetWriter::create(dir, &rig3(), image_info(), CameraSettings::default(), false)
            .unwrap();
    for k in 0..lights {
        w.add_frame(
            FrameKind::Light,
            Some(k),
            &light_file_name(k, "png"),
            &frame_bytes(1000 + k as u16),
        )
        .unwrap();
    }
    w
}

#[test]
fn a_written_set_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    write_set(dir.path(), 3);
    let set = CaptureSet::open(dir.path(), None).unwrap();
    let frames = set.load_frames(&Silent).unwrap();
    assert_eq!(frames.lights.len(), 3);
    let expected = (1002.0 - 600.0) / 15000.0;
    assert!((frames.lights[2].rgb.g.data[0] as f64 - expected).abs() < 1e-7);
}

#[test]
fn an_interrupted_set_keeps_its_frames_and_names_the_missing_ones() {
    let dir = tempfile::tempdir().unwrap();
    write_set(dir.path(), 2);
    let set = CaptureSet::open(dir.path(), None).unwrap();
    assert_eq!(set.manifest.frames.len(), 2);
    let err = set.load_frames(&Silent).unwrap_err().to_string();
    assert!(err.contains("missing frames for lights [2]"), "{err}");
}

#[test]
fn an_existing_set_is_not_overwritten_without_force() {
    let dir = tempfile::tempdir().unwrap();
    write_set(dir.path(), 3);
    let err = CaptureSetWriter::create(
        dir.path(),
        &rig3(),
        image_info(),
        CameraSettings::default(),
        false,
    )
    .err()
    .unwrap();
    assert!(matches!(err, Error::Exists { .. }), "{err}");
    assert!(CaptureSetWriter::create(
        dir.path(),
        &rig3(),
        image_info(),
        CameraSettings::default(),
        true
    )
    .is_ok());
}

#[test]
fn a_damaged_frame_is_named() {
    let dir = tempfile::tempdir().unwrap();
    write_set(dir.path(), 3);
    std::fs::write(dir.path().join("L01.png"), frame_bytes(2000)).unwrap();
    let set = CaptureSet::open(dir.path(), None).unwrap();
    let err = set.load_frames(&Silent).unwrap_err().to_string();
    assert!(err.contains("L01.png") && err.contains("SHA-256"), "{err}");
}

#[test]
fn a_frame_of_the_wrong_size_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let mut w = write_set(dir.path(), 3);
    let big = encode_png16(&DnImage {
        width: 3,
        height: 2,
        data: vec![700; 18],
    })
    .unwrap();
    w.add_frame(FrameKind::Light, Some(1), "L01.png", &big)
        .unwrap();
    let set = CaptureSet::open(dir.path(), None).unwrap();
    let err = set.load_frames(&Silent).unwrap_err().to_string();
    assert!(err.contains("L01.png") && err.contains("3x2"), "{err}");
}

#[test]
fn a_frame_that_is_a_link_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    write_set(dir.path(), 3);
    let target = dir.path().join("elsewhere.png");
    std::fs::rename(dir.path().join("L00.png"), &target).unwrap();
    std::os::unix::fs::symlink(&target, dir.path().join("L00.png")).unwrap();
    let set = CaptureSet::open(dir.path(), None).unwrap();
    let err = set.load_frames(&Silent).unwrap_err().to_string();
    assert!(err.contains("L00.png") && err.contains("link"), "{err}");
}

#[test]
fn resume_keeps_intact_frames_and_drops_damaged_or_missing_ones() {
    let dir = tempfile::tempdir().unwrap();
    write_set(dir.path(), 3);
    std::fs::write(dir.path().join("L00.png"), frame_bytes(4321)).unwrap();
    std::fs::remove_file(dir.path().join("L02.png")).unwrap();
    let (writer, dropped) = CaptureSetWriter::resume(dir.path()).unwrap();
    let files: Vec<&str> = dropped.iter().map(|d| d.file.as_str()).collect();
    assert_eq!(files, ["L00.png", "L02.png"]);
    assert!(dropped[0].reason.contains("SHA-256"), "{:?}", dropped[0]);
    assert_eq!(writer.manifest().frames.len(), 1);
    // The manifest on disk no longer claims the dropped frames.
    let set = CaptureSet::open(dir.path(), None).unwrap();
    assert_eq!(set.manifest.frames.len(), 1);
    assert_eq!(set.manifest.frames[0].file, "L01.png");
}

#[test]
fn a_folder_without_manifest_is_not_a_set() {
    let dir = tempfile::tempdir().unwrap();
    let err = CaptureSet::open(dir.path(), None)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("not a capture set"), "{err}");
}

/// A dn16 frame that is not a PNG (a 16-bit TIFF) takes the whole-file path: it reads back
/// as the PNG frame does, and a changed one is named as changed.
#[test]
fn a_tiff_frame_reads_back_and_a_changed_one_is_named() {
    let tiff = |value: u16| {
        let image =
            image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(2, 2, vec![value; 12]).unwrap();
        let mut bytes = Vec::new();
        image::DynamicImage::ImageRgb16(image)
            .write_to(
                &mut std::io::Cursor::new(&mut bytes),
                image::ImageFormat::Tiff,
            )
            .unwrap();
        bytes
    };
    let dir = tempfile::tempdir().unwrap();
    let mut w = write_set(dir.path(), 3);
    w.add_frame(FrameKind::Light, Some(1), "L01.tif", &tiff(1001))
        .unwrap();
    let set = CaptureSet::open(dir.path(), None).unwrap();
    let frames = set.load_frames(&Silent).unwrap();
    let expected = (1001.0 - 600.0) / 15000.0;
    assert!((frames.lights[1].rgb.g.data[3] as f64 - expected).abs() < 1e-7);

    std::fs::write(dir.path().join("L01.tif"), tiff(2000)).unwrap();
    let err = set.load_frames(&Silent).unwrap_err().to_string();
    assert!(err.contains("L01.tif") && err.contains("SHA-256"), "{err}");
}
