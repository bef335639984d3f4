use std::io::Write;

use super::*;

#[test]
fn atomic_write_replaces_the_whole_file_and_leaves_no_temporary() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("a.txt");
    write_atomic(&path, b"first").unwrap();
    write_atomic(&path, b"second").unwrap();
    assert_eq!(fs::read(&path).unwrap(), b"second");
    let names: Vec<_> = fs::read_dir(dir.path()).unwrap().collect();
    assert_eq!(names.len(), 1);
}

#[test]
fn atomic_write_into_a_missing_folder_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("missing").join("a.txt");
    let err = write_atomic(&path, b"x").unwrap_err().to_string();
    assert!(err.contains("a.txt"), "{err}");
}

#[test]
fn a_staged_folder_appears_whole_or_not_at_all() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("maps");
    // Dropped before commit (a failure half-way): nothing remains.
    let stage = StagedDir::create(&out, false, &[]).unwrap();
    fs::write(stage.path().join("normal.png"), b"half").unwrap();
    drop(stage);
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 0);

    let stage = StagedDir::create(&out, false, &[]).unwrap();
    fs::write(stage.path().join("report.json"), b"1").unwrap();
    stage.commit(false, &[]).unwrap();
    assert_eq!(fs::read(out.join("report.json")).unwrap(), b"1");
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);

    // An existing output needs force, and is then replaced as a whole.
    let err = StagedDir::create(&out, false, &[]).err().unwrap();
    assert!(matches!(err, Error::Exists { .. }), "{err}");
    let stage = StagedDir::create(&out, true, &[]).unwrap();
    fs::write(stage.path().join("report.json"), b"2").unwrap();
    stage.commit(true, &[]).unwrap();
    assert_eq!(fs::read(out.join("report.json")).unwrap(), b"2");
    // report.json and the ownership record.
    assert_eq!(fs::read_dir(&out).unwrap().count(), 2);
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn a_copied_in_record_or_report_is_no_proof_of_ownership() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("maps");
    let stage = StagedDir::create(&out, false, &[]).unwrap();
    fs::write(stage.path().join("report.json"), b"1").unwrap();
    fs::create_dir(stage.path().join("sub")).unwrap();
    fs::write(stage.path().join("sub/a.exr"), b"a").unwrap();
    stage.commit(false, &[]).unwrap();
    // A user's file at the top, or inside a sub-folder psscan wrote: refused, kept.
    for extra in ["notes.txt", "sub/notes.txt"] {
        fs::write(out.join(extra), b"mine").unwrap();
        let err = StagedDir::create(&out, true, &[])
            .err()
            .unwrap()
            .to_string();
        assert!(
            err.contains(extra) && err.contains("did not write"),
            "{err}"
        );
        assert_eq!(fs::read(out.join(extra)).unwrap(), b"mine");
        fs::remove_file(out.join(extra)).unwrap();
    }
    // A user folder with a report.json and the record copied in from psscan's output.
    let user = dir.path().join("user");
    fs::create_dir(&user).unwrap();
    for f in ["report.json", OWNED_FILE] {
        fs::copy(out.join(f), user.join(f)).unwrap();
    }
    fs::write(user.join("frame.png"), b"mine").unwrap();
    let err = StagedDir::create(&user, true, &[])
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("frame.png"), "{err}");
    // Without the record: not a psscan output.
    fs::remove_file(user.join(OWNED_FILE)).unwrap();
    let err = StagedDir::create(&user, true, &[])
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("not a psscan output"), "{err}");
    assert_eq!(fs::read_dir(&user).unwrap().count(), 2);
}

#[test]
fn an_output_that_is_holds_or_sits_inside_an_input_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("set");
    fs::create_dir(&input).unwrap();
    let inside = input.join("maps");
    let dotted = dir.path().join("other/../set");
    for (out, why) in [
        (input.clone(), "is an input"),
        (dotted, "is an input"),
        (dir.path().to_path_buf(), "holds an input"),
        (inside, "sits inside an input"),
    ] {
        let err = check_replaceable(&out, true, &[&input])
            .unwrap_err()
            .to_string();
        assert!(err.contains(why), "{}: {err}", out.display());
    }
    assert!(check_replaceable(&dir.path().join("maps"), true, &[&input]).is_ok());
}

#[test]
fn staging_left_by_a_dead_process_is_removed_and_a_live_ones_kept() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("maps");
    // No process has id 0x7fff_fff0 (above Linux's pid_max); this process is alive.
    let dead = dir
        .path()
        .join(format!("maps.partial-{}-0", 0x7fff_fff0u32));
    let live = dir
        .path()
        .join(format!("maps.partial-{}-99", std::process::id()));
    let other = dir
        .path()
        .join(format!("maps2.partial-{}-0", 0x7fff_fff0u32));
    for d in [&dead, &live, &other] {
        fs::create_dir(d).unwrap();
    }
    remove_stale_staging(&out);
    assert!(!dead.exists());
    assert!(live.exists() && other.exists());
}

#[test]
fn staging_names() {
    assert_eq!(staging_owner("L00.png.tmp-42-7"), Some(42));
    assert_eq!(staging_owner("my-set.partial-42-0"), Some(42));
    assert_eq!(staging_owner("maps.old-1-2"), Some(1));
    assert_eq!(staging_owner("notes-1-2.txt"), None);
    assert_eq!(staging_owner("maps.partial-x-2"), None);
}

#[test]
fn a_folder_of_other_files_is_never_replaced() {
    let dir = tempfile::tempdir().unwrap();
    fs::write(dir.path().join("thesis.tex"), b"precious").unwrap();
    let err = StagedDir::create(dir.path(), true, &[])
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("not a psscan output"), "{err}");
    // An empty folder is fine.
    let empty = dir.path().join("empty");
    fs::create_dir(&empty).unwrap();
    assert!(StagedDir::create(&empty, false, &[]).is_ok());
}

#[test]
fn sha256_of_known_input() {
    assert_eq!(
        sha256_hex(b"abc"),
        "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    );
}

#[test]
fn an_atomic_file_appears_only_when_committed_and_leaves_nothing_when_dropped() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("map.exr");
    std::fs::write(&path, b"old").unwrap();
    let entries = || -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };

    // An encoder that fails half-way: the old file stays, no temporary file is left, and
    // nothing is left registered for an interrupt to remove.
    let mut failed = AtomicFile::create(&path).unwrap();
    failed.writer().write_all(b"half").unwrap();
    assert_eq!(entries().len(), 2, "{:?}", entries());
    drop(failed);
    assert_eq!(entries(), ["map.exr"]);
    assert_eq!(std::fs::read(&path).unwrap(), b"old");
    assert!(!staging().iter().any(|p| p.starts_with(dir.path())));

    let mut done = AtomicFile::create(&path).unwrap();
    done.writer().write_all(b"new bytes").unwrap();
    assert_eq!(
        std::fs::read(&path).unwrap(),
        b"old",
        "visible before the commit"
    );
    done.commit().unwrap();
    assert_eq!(entries(), ["map.exr"]);
    assert_eq!(std::fs::read(&path).unwrap(), b"new bytes");
    assert!(!staging().iter().any(|p| p.starts_with(dir.path())));

    let missing = dir.path().join("no such folder").join("x.png");
    let err = AtomicFile::create(&missing).err().unwrap().to_string();
    assert!(err.contains("x.png"), "{err}");
}
