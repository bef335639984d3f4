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

/// A stopped run names what it had already put in place (the registry is per process and
/// other tests commit too: only this test's folders are looked for).
#[test]
fn a_committed_output_is_recorded_with_the_earlier_output_it_replaced() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("maps");
    let ours = |c: &CommittedOutput| c.path == out;
    let stage = StagedDir::create(&out, false, &[]).unwrap();
    assert!(!committed_outputs().iter().any(ours));
    stage.commit(false, &[]).unwrap();
    let first: Vec<_> = committed_outputs().into_iter().filter(ours).collect();
    assert_eq!(first.len(), 1);
    assert_eq!(first[0].replaced, None);
    let stage = StagedDir::create(&out, true, &[]).unwrap();
    stage.commit(true, &[]).unwrap();
    let both: Vec<_> = committed_outputs().into_iter().filter(ours).collect();
    assert_eq!(both.len(), 2);
    let set_aside = both[1]
        .replaced
        .as_ref()
        .expect("the first output was replaced");
    assert!(
        set_aside.starts_with(dir.path()) && !set_aside.exists(),
        "{set_aside:?}"
    );
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
    atomic_file_appears_only_when_committed(AtomicFile::create);
    // The same, past the page cache.
    atomic_file_appears_only_when_committed(AtomicFile::create_uncached);
}

fn atomic_file_appears_only_when_committed(create: fn(&Path) -> Result<AtomicFile>) {
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
    let mut failed = create(&path).unwrap();
    failed.writer().write_all(b"half").unwrap();
    assert_eq!(entries().len(), 2, "{:?}", entries());
    drop(failed);
    assert_eq!(entries(), ["map.exr"]);
    assert_eq!(std::fs::read(&path).unwrap(), b"old");
    assert!(!staging().iter().any(|p| p.starts_with(dir.path())));

    let mut done = create(&path).unwrap();
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
    let err = create(&missing).err().unwrap().to_string();
    assert!(err.contains("x.png"), "{err}");
}

/// A [`DirectFile`] in blocks of 4096 bytes, given writes of many sizes, seeks back before the
/// block being filled (patches), seeks past the end (gaps of zeros) and seeks from the end,
/// holds what an in-memory file given the same calls holds.
#[test]
fn a_direct_file_holds_what_a_file_in_memory_holds_after_the_same_writes_and_seeks() {
    use std::io::{Cursor, Seek, SeekFrom};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("direct.bin");
    let mut state = 12345u64;
    let mut next = |n: u64| {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (state >> 33) % n
    };
    for round in 0..6 {
        let mut direct = DirectFile::with_block_size(&path, 4096).unwrap();
        let mut memory = Cursor::new(Vec::new());
        for step in 0..300 {
            let seek = match next(10) {
                0 => Some(SeekFrom::Start(next(memory.get_ref().len() as u64 + 1))),
                1 => Some(SeekFrom::Current(next(9000) as i64)),
                2 => Some(SeekFrom::End(
                    -(next(memory.get_ref().len() as u64 + 1) as i64),
                )),
                _ => None,
            };
            if let Some(to) = seek {
                assert_eq!(direct.seek(to).unwrap(), memory.seek(to).unwrap());
            }
            // Up to three blocks at once, and sometimes exactly to a block's end.
            let len = match next(4) {
                0 => 4096 - (memory.position() % 4096) as usize,
                _ => next(3 * 4096) as usize,
            };
            let bytes: Vec<u8> = (0..len).map(|i| (i as u64 + step + round) as u8).collect();
            direct.write_all(&bytes).unwrap();
            memory.write_all(&bytes).unwrap();
        }
        // The last seek leaves the position where it is: the length is the furthest write.
        let end = memory.get_ref().len() as u64;
        direct.seek(SeekFrom::Start(end + 100)).unwrap();
        drop(direct.finish().unwrap());
        let on_disk = fs::read(&path).unwrap();
        assert_eq!(on_disk.len(), memory.get_ref().len(), "round {round}");
        assert!(on_disk == *memory.get_ref(), "round {round}: bytes differ");
    }
}

/// A seek before the start is refused, as a file's is.
#[test]
fn a_direct_file_refuses_a_seek_before_its_start() {
    use std::io::{Seek, SeekFrom};
    let dir = tempfile::tempdir().unwrap();
    let mut direct = DirectFile::create(&dir.path().join("x")).unwrap();
    direct.write_all(b"abc").unwrap();
    assert!(direct.seek(SeekFrom::Current(-4)).is_err());
    assert_eq!(direct.seek(SeekFrom::End(-3)).unwrap(), 0);
}
