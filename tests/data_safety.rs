//! Nothing a user owns is lost, through the real binary: `--force` (and the writers that
//! replace their own folder) refuses a folder psscan did not wholly write, and any folder
//! that is, holds or sits inside an input of the run, for every writer; SIGINT and SIGTERM
//! remove what the run staged and exit 130 / 143; staging a killed run left is removed by the
//! next one.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use psscan::calibration::steps::{PixelToWorldCheck, TableStep};
use psscan::calibration::table::TablePose;
use psscan::rig::Board;
use psscan::rig::Rig;
use psscan::sim::emulator::{Emulator, EmulatorFiles};

mod common;
use common::{psscan, s, stderr};

/// A small scene: renders and solves in a fraction of a second.
const SMALL: [&str; 7] = ["--width", "32", "--height", "24", "--step", "32", "-q"];

/// Every file under `dir` with its bytes (relative paths).
fn snapshot(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    fn walk(root: &Path, dir: &Path, out: &mut BTreeMap<PathBuf, Vec<u8>>) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                walk(root, &path, out);
            } else {
                let rel = path.strip_prefix(root).unwrap().to_path_buf();
                out.insert(rel, std::fs::read(&path).unwrap());
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

/// Runs psscan with `args`, which must be refused: exit 1, the message names `cause`, and
/// every file under `kept` is still there byte for byte (nothing added either).
fn assert_refused(args: &[&str], cause: &str, kept: &Path) {
    let before = snapshot(kept);
    let out = psscan(args);
    let err = stderr(&out);
    assert_eq!(
        out.status.code(),
        Some(1),
        "{args:?} was not refused: {err}"
    );
    assert!(
        err.contains(cause),
        "{args:?}: {err} does not name {cause:?}"
    );
    assert!(
        before == snapshot(kept),
        "{args:?} changed {}",
        kept.display()
    );
}

fn ok(out: &Output) {
    assert!(out.status.success(), "{}", stderr(out));
}

fn synth(out: &Path) {
    let mut args = vec!["synth", "--out", s(out)];
    args.extend(SMALL);
    ok(&psscan(&args));
}

/// A user's folder that looks like a psscan output: a `report.json` copied in (and the
/// ownership record of a real output too), beside the user's own notes.
fn user_folder(at: &Path, from_output: &Path) -> PathBuf {
    std::fs::create_dir_all(at).unwrap();
    for f in ["report.json", ".psscan-owned.json"] {
        std::fs::copy(from_output.join(f), at.join(f)).unwrap();
    }
    std::fs::write(at.join("notes.txt"), b"thread count 48/cm, do not lose").unwrap();
    at.to_path_buf()
}

/// A set and a solve of it, in `root`.
fn set_and_maps(root: &Path) -> (PathBuf, PathBuf) {
    let set = root.join("set");
    let maps = root.join("maps");
    synth(&set);
    ok(&psscan(&["solve", s(&set), "--out", s(&maps), "-q"]));
    (set, maps)
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for (rel, bytes) in snapshot(from) {
        let path = to.join(rel);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, bytes).unwrap();
    }
}

#[test]
fn solve_force_never_replaces_a_user_folder_or_an_input() {
    let tmp = tempfile::tempdir().unwrap();
    let (set, maps) = set_and_maps(tmp.path());
    std::fs::write(set.join("notes.txt"), b"mine").unwrap();
    let user = user_folder(&tmp.path().join("user"), &maps);
    fn solve<'a>(set: &'a Path, out: &'a Path) -> Vec<&'a str> {
        vec!["solve", s(set), "--out", s(out), "--force", "-q"]
    }

    // (a) A folder with a copied-in report.json (and record) and the user's notes.
    assert_refused(
        &solve(&set, &user),
        "notes.txt, which psscan did not write",
        &user,
    );
    // (b) The set solved into itself (also with a report.json copied into the set).
    std::fs::copy(maps.join("report.json"), set.join("report.json")).unwrap();
    assert_refused(&solve(&set, &set), "is an input of this run", &set);
    // (c) Into an earlier psscan output that sits inside the set ...
    copy_dir(&maps, &set.join("maps"));
    assert_refused(
        &solve(&set, &set.join("maps")),
        "sits inside an input",
        &set,
    );
    // ... and into a psscan output that holds the set (`solve out/x/myset --out out/x`).
    let x = tmp.path().join("x");
    copy_dir(&maps, &x);
    copy_dir(&set, &x.join("myset"));
    let inner = x.join("myset");
    assert_refused(
        &["solve", s(&inner), "--out", s(&x), "--force", "-q"],
        "holds an input of this run",
        &x,
    );
    // The same, spelt with `..`: canonical paths are compared.
    let dotted = x.join("myset/../myset");
    assert_refused(
        &["solve", s(&inner), "--out", s(&dotted), "--force"],
        "is an input",
        &x,
    );

    // A psscan output is still replaced with --force, whole.
    ok(&psscan(&solve(&set, &maps)));
    assert!(maps.join("report.json").is_file());
}

#[test]
fn a_batch_never_solves_one_set_over_another() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    synth(&a);
    synth(&b);
    // Each set's output folder (ROOT/<name>) is the set itself.
    assert_refused(
        &[
            "solve",
            s(&a),
            s(&b),
            "--out",
            s(tmp.path()),
            "--force",
            "-q",
        ],
        "is an input of this run",
        tmp.path(),
    );
    // One set's output (OUT/x, for a set named x) would hold the other set (OUT/x/inner).
    let out = tmp.path().join("out");
    let x = tmp.path().join("src/x");
    synth(&x);
    let inner = out.join("x/inner");
    synth(&inner);
    assert_refused(
        &["solve", s(&x), s(&inner), "--out", s(&out), "--force", "-q"],
        "holds an input",
        &out.join("x"),
    );
    assert!(inner.join("manifest.toml").is_file());
}

#[test]
fn synth_force_never_replaces_a_user_folder_or_its_rig() {
    let tmp = tempfile::tempdir().unwrap();
    let (set, maps) = set_and_maps(tmp.path());
    let user = user_folder(&tmp.path().join("user"), &maps);
    let synth_into = |out: &Path, extra: &[&str]| {
        let mut args = vec!["synth", "--out", s(out), "--force"];
        args.extend(extra);
        args.extend(SMALL);
        args.iter().map(|a| a.to_string()).collect::<Vec<_>>()
    };
    let refuse = |args: Vec<String>, cause: &str, kept: &Path| {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        assert_refused(&args, cause, kept)
    };
    // (a) The user's folder; also a capture set the user added notes to.
    refuse(synth_into(&user, &[]), "notes.txt", &user);
    std::fs::write(set.join("truth/notes.txt"), b"mine").unwrap();
    refuse(synth_into(&set, &[]), "truth/notes.txt", &set);
    // (b) Over its own input (the rig file), (c) into the folder that holds it, or inside it.
    let rigs = tmp.path().join("rigs");
    std::fs::create_dir(&rigs).unwrap();
    let rig = rigs.join("rig.toml");
    Rig::default_rig().save(&rig).unwrap();
    refuse(synth_into(&rig, &["--rig", s(&rig)]), "is an input", &rigs);
    refuse(
        synth_into(&rigs, &["--rig", s(&rig)]),
        "holds an input",
        &rigs,
    );
    std::fs::remove_file(set.join("truth/notes.txt")).unwrap();
    refuse(
        synth_into(
            &set.join("truth"),
            &["--rig", s(&set.join("truth/rig.toml"))],
        ),
        "holds an input",
        &set,
    );
}

#[test]
fn demo_replaces_only_its_own_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let (_, maps) = set_and_maps(tmp.path());
    let user = user_folder(&tmp.path().join("user"), &maps);
    let demo = |out: &Path| {
        let mut args = vec!["demo", "--out", s(out)];
        args.extend(SMALL);
        args.iter().map(|a| a.to_string()).collect::<Vec<_>>()
    };
    let args = demo(&user);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    assert_refused(&args, "notes.txt, which psscan did not write", &user);
    // Its own folder is replaced as a whole; a note added inside it is not lost.
    let own = tmp.path().join("demo");
    let args = demo(&own);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    ok(&psscan(&args));
    ok(&psscan(&args));
    std::fs::write(own.join("maps/notes.txt"), b"mine").unwrap();
    assert_refused(&args, "maps/ that holds notes.txt", &own);
}

/// A table step result (the camera where the default rig puts it): enough for a bundle.
fn table_step(path: &Path) {
    let rig = Rig::default_rig();
    let step = TableStep {
        image: "table.png".into(),
        board: Board::parse("9x6", 15.0).unwrap(),
        pose: TablePose {
            camera_position_m: rig.camera.position_m,
            camera_rotation_deg: rig.camera.rotation_deg,
            rms_reprojection_px: 0.1,
        },
        check: PixelToWorldCheck {
            corners: 54,
            mean_mm: 0.05,
            max_mm: 0.1,
            area_mm: [120.0, 75.0],
        },
    };
    std::fs::write(path, toml::to_string(&step).unwrap()).unwrap();
}

#[test]
fn calibrate_bundle_force_never_replaces_a_user_folder_or_its_steps() {
    let tmp = tempfile::tempdir().unwrap();
    let (_, maps) = set_and_maps(tmp.path());
    let steps = tmp.path().join("steps");
    std::fs::create_dir(&steps).unwrap();
    let table = steps.join("table.toml");
    table_step(&table);
    let bundle = |out: &Path| {
        vec![
            "calibrate",
            "bundle",
            "--table",
            s(&table),
            "--name",
            "t",
            "--out",
            s(out),
            "--force",
        ]
        .into_iter()
        .map(String::from)
        .collect::<Vec<_>>()
    };
    let refuse = |out: &Path, cause: &str, kept: &Path| {
        let args = bundle(out);
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        assert_refused(&args, cause, kept)
    };
    let user = user_folder(&tmp.path().join("user"), &maps);
    refuse(&user, "notes.txt", &user);
    refuse(&table, "is an input", &steps);
    refuse(&steps, "holds an input", &steps);
}

#[test]
fn bench_out_never_replaces_a_user_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let (_, maps) = set_and_maps(tmp.path());
    let user = user_folder(&tmp.path().join("user"), &maps);
    // Refused before the (long) run starts.
    assert_refused(
        &["bench", "--out", s(&user), "--sizes", "0.01", "--no-numpy"],
        "notes.txt",
        &user,
    );
}

fn emulator(dir: &Path) -> Emulator {
    let files = EmulatorFiles::locate().expect("make -C firmware all sim");
    Emulator::start(&files, &dir.join("pins.log")).unwrap()
}

fn capture_args<'a>(
    out: &'a Path,
    emu: &'a Emulator,
    pins: &'a Path,
    settle: &'a str,
) -> Vec<&'a str> {
    vec![
        "capture",
        "--out",
        s(out),
        "--port",
        emu.pty(),
        "--camera",
        "sim",
        "--pin-log",
        s(pins),
        "--settle-ms",
        settle,
        "--width",
        "32",
        "--height",
        "24",
        "--step",
        "64",
        "-q",
    ]
}

#[test]
fn capture_force_never_replaces_a_user_folder_or_its_rig() {
    let tmp = tempfile::tempdir().unwrap();
    let (set, maps) = set_and_maps(tmp.path());
    let emu = emulator(tmp.path());
    let pins = tmp.path().join("pins.log");
    let user = user_folder(&tmp.path().join("user"), &maps);
    let with_force = |out: &Path, extra: &[&str]| {
        let mut args = capture_args(out, &emu, &pins, "1");
        args.push("--force");
        args.extend_from_slice(extra);
        args.iter().map(|a| a.to_string()).collect::<Vec<_>>()
    };
    let refuse = |args: Vec<String>, cause: &str, kept: &Path| {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        assert_refused(&args, cause, kept)
    };
    refuse(with_force(&user, &[]), "notes.txt", &user);
    // Without --force a user's folder is not written into either.
    let args = capture_args(&user, &emu, &pins, "1");
    assert_refused(&args, "notes.txt", &user);
    let rig = set.join("rig.toml");
    refuse(
        with_force(&set, &["--rig", s(&rig)]),
        "holds an input",
        &set,
    );
    // A set psscan captured is started over with --force.
    let own = tmp.path().join("captured");
    ok(&psscan(&capture_args(&own, &emu, &pins, "1")));
    ok(&psscan(
        &with_force(&own, &[])
            .iter()
            .map(String::as_str)
            .collect::<Vec<_>>(),
    ));
}

/// Starts psscan with `args`, its stderr piped.
fn spawn(args: &[&str]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_psscan"))
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Staging folders and temporary files beside or inside `dir`'s parent.
fn staging_in(root: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap().flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.contains(".partial-") || name.contains(".tmp-") || name.contains(".old-") {
                found.push(entry.path());
            }
            if entry.path().is_dir() {
                stack.push(entry.path());
            }
        }
    }
    found
}

/// Waits until a staging folder for `out` appears (the run is under way), then sends
/// `signal`.
fn signal_when_staging(child: &Child, root: &Path, out: &Path, signal: i32) {
    let prefix = format!("{}.partial-", out.file_name().unwrap().to_string_lossy());
    let start = Instant::now();
    while !std::fs::read_dir(root)
        .unwrap()
        .flatten()
        .any(|e| e.file_name().to_string_lossy().starts_with(&prefix))
    {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "no staging appeared"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
    send(child, signal);
}

fn send(child: &Child, signal: i32) {
    // SAFETY: signalling our own child.
    unsafe {
        libc::kill(child.id() as libc::pid_t, signal);
    }
}

const LARGE: [&str; 5] = ["--width", "512", "--height", "384", "-q"];

#[test]
fn sigint_during_synth_leaves_no_half_written_set_and_keeps_the_old_one() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("set");
    synth(&out);
    let before = snapshot(&out);
    let mut args = vec!["synth", "--out", s(&out), "--force"];
    args.extend(LARGE);
    let child = spawn(&args);
    signal_when_staging(&child, tmp.path(), &out, libc::SIGINT);
    let done = child.wait_with_output().unwrap();
    let err = stderr(&done);
    assert_eq!(done.status.code(), Some(130), "{err}");
    assert!(
        err.contains("SIGINT") && err.contains("stopped `psscan synth`"),
        "{err}"
    );
    assert!(
        err.contains("removed unfinished") && err.contains(".partial-"),
        "{err}"
    );
    assert_eq!(staging_in(tmp.path()), Vec::<PathBuf>::new());
    assert!(before == snapshot(&out), "the previous set changed");
}

#[test]
fn sigterm_during_solve_removes_the_staged_maps_and_exits_143() {
    let tmp = tempfile::tempdir().unwrap();
    let set = tmp.path().join("set");
    let mut args = vec!["synth", "--out", s(&set)];
    args.extend(LARGE);
    ok(&psscan(&args));
    let maps = tmp.path().join("maps");
    let child = spawn(&["solve", s(&set), "--out", s(&maps), "-q"]);
    signal_when_staging(&child, tmp.path(), &maps, libc::SIGTERM);
    let done = child.wait_with_output().unwrap();
    let err = stderr(&done);
    assert_eq!(done.status.code(), Some(143), "{err}");
    assert!(
        err.contains("SIGTERM") && err.contains("stopped `psscan solve`"),
        "{err}"
    );
    assert_eq!(staging_in(tmp.path()), Vec::<PathBuf>::new());
    assert!(!maps.exists());
}

/// Stopped between two sets of a batch: the set already solved is in place and the message
/// says so (it had called the earlier output under every name untouched).
#[test]
fn sigint_between_the_sets_of_a_batch_names_the_finished_output() {
    let tmp = tempfile::tempdir().unwrap();
    let sets = ["a", "b"].map(|name| tmp.path().join(name));
    for set in &sets {
        let mut args = vec!["synth", "--out", s(set)];
        args.extend(LARGE);
        ok(&psscan(&args));
    }
    let maps = tmp.path().join("maps");
    let child = spawn(&["solve", s(&sets[0]), s(&sets[1]), "--out", s(&maps), "-q"]);
    // Signal once one set's output is in place and the other's is staged.
    let start = Instant::now();
    let finished = loop {
        let staged = |name: &str| {
            let prefix = format!("{name}.partial-");
            std::fs::read_dir(&maps).is_ok_and(|entries| {
                entries
                    .flatten()
                    .any(|e| e.file_name().to_string_lossy().starts_with(&prefix))
            })
        };
        let done = |name: &str| maps.join(name).join("report.json").is_file();
        if let Some((finished, _)) = [("a", "b"), ("b", "a")]
            .into_iter()
            .find(|&(one, other)| done(one) && staged(other))
        {
            break maps.join(finished);
        }
        assert!(start.elapsed() < Duration::from_secs(60), "no such moment");
        std::thread::sleep(Duration::from_millis(1));
    };
    send(&child, libc::SIGINT);
    let done = child.wait_with_output().unwrap();
    let err = stderr(&done);
    assert_eq!(done.status.code(), Some(130), "{err}");
    assert!(
        err.contains(&format!(
            "finished before the stop and in place: {}",
            finished.display()
        )),
        "{err}"
    );
    assert!(
        err.contains("removed unfinished") && err.contains(".partial-"),
        "{err}"
    );
    assert!(err.contains("kept: everything else"), "{err}");
    assert!(finished.join("report.json").is_file());
    assert_eq!(staging_in(tmp.path()), Vec::<PathBuf>::new());
}

#[test]
fn staging_a_killed_synth_left_is_removed_by_the_next_run() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("set");
    let mut args = vec!["synth", "--out", s(&out)];
    args.extend(LARGE);
    let mut child = spawn(&args);
    signal_when_staging(&child, tmp.path(), &out, libc::SIGKILL);
    child.wait().unwrap();
    let left = staging_in(tmp.path());
    assert_eq!(left.len(), 1, "{left:?}");
    let pid = child.id().to_string();
    let mut args = vec!["synth", "--out", s(&out)];
    args.extend(SMALL);
    let again = psscan(&args);
    ok(&again);
    let err = stderr(&again);
    assert!(
        err.contains("removed") && err.contains(&pid) && err.contains("no longer runs"),
        "{err}"
    );
    assert_eq!(staging_in(tmp.path()), Vec::<PathBuf>::new());
}

#[test]
fn sigterm_during_capture_switches_the_leds_off_keeps_the_frames_and_exits_143() {
    let tmp = tempfile::tempdir().unwrap();
    let emu = emulator(tmp.path());
    let pins = tmp.path().join("pins.log");
    let set = tmp.path().join("set");
    let child = spawn(&capture_args(&set, &emu, &pins, "300"));
    let start = Instant::now();
    while psscan::capture::CaptureSet::open(&set, None)
        .map(|s| s.manifest.frames.len())
        .unwrap_or(0)
        < 4
    {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "capture did not progress"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    // SAFETY: signalling our own child.
    unsafe {
        libc::kill(child.id() as libc::pid_t, libc::SIGTERM);
    }
    let done = child.wait_with_output().unwrap();
    let err = stderr(&done);
    use std::os::unix::process::ExitStatusExt;
    assert_eq!(
        done.status.code(),
        Some(143),
        "{err} {:?}",
        done.status.signal()
    );
    assert!(err.contains("SIGTERM") && err.contains("--resume"), "{err}");
    assert!(emu.pin_log().lit().unwrap().is_empty(), "LEDs off");
    let kept = psscan::capture::CaptureSet::open(&set, None).unwrap();
    assert!(kept.manifest.frames.len() >= 4);
    assert_eq!(staging_in(tmp.path()), Vec::<PathBuf>::new());
}
