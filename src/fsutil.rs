//! File-system helpers shared by every writer: atomic writes (so a crash never leaves a
//! half-written file under its final name), SHA-256 of files, and the one rule for what an
//! output may replace.
//!
//! The rule (every writer goes through [`check_replaceable`], by [`StagedDir`] or
//! [`claim_dir`]): an output folder may be replaced only when psscan wrote it and every entry
//! in it (its ownership record, [`OWNED_FILE`], lists them: a `report.json` or a manifest a
//! user copied in is no proof), only with `force` (or for writers whose folder is their own
//! scratch space), and never when it is, holds or sits inside an input of the same run.
//! Anything else is refused with the reason, before anything is written or removed.
//!
//! Everything a run stages (`OUT.partial-PID-N/` folders, `FILE.tmp-PID-N` files) is
//! registered here, so a signal handler can remove it ([`remove_staging`]); staging left by a
//! process that no longer runs (killed) is removed by the next writer beside it.

use std::collections::BTreeSet;
use std::fs;
use std::path::{Component, Path, PathBuf};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::error::{Error, Result};

mod atomic;
mod direct;

pub use atomic::{write_atomic, AtomicFile, FileWriter};
pub use direct::{DirectFile, BLOCK as DIRECT_BLOCK};

/// The ownership record psscan keeps in every folder it writes: the entries it wrote.
pub const OWNED_FILE: &str = ".psscan-owned.json";

/// Paths this process is staging (partial folders, temporary files) and would leave behind
/// if it stopped now.
static STAGING: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// Folders this process has claimed (emptied or created for a new output): claiming one
/// again in the same run keeps what the run has written there since.
static CLAIMED: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// Output folders this process has put in place ([`StagedDir::commit`]), for the message of
/// a run stopped after that: they are the new outputs, not unfinished ones.
static COMMITTED: Mutex<Vec<CommittedOutput>> = Mutex::new(Vec::new());

/// An output folder a run put in place.
#[derive(Clone, Debug, PartialEq)]
pub struct CommittedOutput {
    /// Where the output now is.
    pub path: PathBuf,
    /// Where the earlier output it replaced was set aside until removed (none: there was
    /// none).
    pub replaced: Option<PathBuf>,
}

/// The output folders this process has put in place so far.
pub fn committed_outputs() -> Vec<CommittedOutput> {
    COMMITTED.lock().unwrap_or_else(|e| e.into_inner()).clone()
}

fn staging() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    STAGING.lock().unwrap_or_else(|e| e.into_inner())
}

fn register(path: &Path) {
    staging().push(path.to_path_buf());
}

fn unregister(path: &Path) {
    staging().retain(|p| p != path);
}

/// Registers a scratch folder or file the run removes when done (a benchmark's temporary
/// sets): a signal handler removes it too ([`remove_staging`]).
pub fn register_scratch(path: &Path) {
    register(path);
}

/// The run removed (or kept) its scratch `path` itself.
pub fn unregister_scratch(path: &Path) {
    unregister(path);
}

/// Removes everything this process is staging (for a signal handler: the run stops, and no
/// half-written output may stay). Holds the registry while it works, so a stage that is
/// being renamed into place finishes first and no new one starts. Returns what it removed.
pub fn remove_staging() -> Vec<PathBuf> {
    let mut list = staging();
    let mut removed = Vec::new();
    for path in list.drain(..) {
        let gone = match fs::symlink_metadata(&path) {
            Ok(m) if m.is_dir() => remove_dir_retrying(&path),
            Ok(_) => fs::remove_file(&path).is_ok(),
            Err(_) => continue,
        };
        if gone {
            removed.push(path);
        }
    }
    // Keep the lock: workers that try to stage more wait until the process exits.
    std::mem::forget(list);
    removed
}

/// `remove_dir_all` while other threads may still be writing into the folder.
fn remove_dir_retrying(path: &Path) -> bool {
    for _ in 0..20 {
        if fs::remove_dir_all(path).is_ok() || !path.exists() {
            return true;
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    false
}

/// A name beside `path` that no other writer uses: `name.tmp-<pid>-<n>`.
fn temp_sibling(path: &Path) -> PathBuf {
    temp_sibling_with(path, "tmp")
}

/// Lower-case hex SHA-256 of a byte slice.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

/// A digest's bytes in lower-case hex, as manifests record SHA-256 sums.
pub fn hex(digest: &[u8]) -> String {
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

/// Lower-case hex SHA-256 of a file's contents.
pub fn sha256_file(path: &Path) -> Result<String> {
    let bytes = fs::read(path).map_err(|e| Error::io(path, e))?;
    Ok(sha256_hex(&bytes))
}

/// Creates a folder and its parents, naming the folder when that fails.
pub fn create_dir_all(path: &Path) -> Result<()> {
    fs::create_dir_all(path).map_err(|e| Error::io(path, e))
}

/// What [`OWNED_FILE`] holds: the entries psscan wrote in the folder, as paths relative to
/// it with `/` between components; `name/` is a sub-folder psscan owns as a whole, checked by
/// its own record.
#[derive(Debug, Default, Serialize, Deserialize)]
struct OwnedRecord {
    written_by: String,
    entries: BTreeSet<String>,
}

/// Adds `entries` (relative paths; `name/` for an owned sub-folder with its own record) to the
/// ownership record of `dir`, creating it. Writers that fill a folder a step at a time (a
/// capture set) record each entry they write; a staged output is recorded whole when it is
/// committed.
pub fn record_owned<I, S>(dir: &Path, entries: I) -> Result<()>
where
    I: IntoIterator<Item = S>,
    S: Into<String>,
{
    let mut record = read_record(dir)?.unwrap_or_else(|| OwnedRecord {
        written_by: format!("psscan {}", env!("CARGO_PKG_VERSION")),
        entries: BTreeSet::new(),
    });
    let before = record.entries.len();
    record.entries.extend(entries.into_iter().map(Into::into));
    if before == record.entries.len() && dir.join(OWNED_FILE).is_file() {
        return Ok(());
    }
    let text = serde_json::to_string_pretty(&record).expect("a record always serialises");
    write_atomic(&dir.join(OWNED_FILE), text.as_bytes())
}

fn read_record(dir: &Path) -> Result<Option<OwnedRecord>> {
    let path = dir.join(OWNED_FILE);
    match fs::read(&path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(Error::io(&path, e)),
        // A record that does not parse proves nothing: the folder counts as someone else's.
        Ok(bytes) => Ok(serde_json::from_slice(&bytes).ok()),
    }
}

/// Every entry under `dir` as its record lists it: files by relative path, sub-folders that
/// hold their own record as `name/` (not descended into).
fn entries_of_tree(dir: &Path) -> Result<BTreeSet<String>> {
    fn walk(root: &Path, rel: &str, out: &mut BTreeSet<String>) -> Result<()> {
        let here = root.join(rel);
        for entry in fs::read_dir(&here).map_err(|e| Error::io(&here, e))? {
            let entry = entry.map_err(|e| Error::io(&here, e))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            let path = if rel.is_empty() {
                name
            } else {
                format!("{rel}/{name}")
            };
            let kind = entry.file_type().map_err(|e| Error::io(entry.path(), e))?;
            if kind.is_dir() && entry.path().join(OWNED_FILE).is_file() {
                out.insert(format!("{path}/"));
            } else if kind.is_dir() {
                walk(root, &path, out)?;
            } else if path != OWNED_FILE {
                out.insert(path);
            }
        }
        Ok(())
    }
    let mut out = BTreeSet::new();
    walk(dir, "", &mut out)?;
    Ok(out)
}

/// Why `dir` is not wholly psscan's, as a phrase ("holds notes.txt, which psscan did not
/// write"), or `None` when psscan wrote every entry in it.
fn foreign_entry(dir: &Path) -> Result<Option<String>> {
    let Some(record) = read_record(dir)? else {
        return Ok(Some(format!(
            "holds no record of what psscan wrote there ({OWNED_FILE}), so it is not a psscan \
             output"
        )));
    };
    walk_foreign(dir, "", &record)
}

fn walk_foreign(root: &Path, rel: &str, record: &OwnedRecord) -> Result<Option<String>> {
    let here = root.join(rel);
    let mut names: Vec<_> = fs::read_dir(&here)
        .map_err(|e| Error::io(&here, e))?
        .collect::<std::io::Result<_>>()
        .map_err(|e| Error::io(&here, e))?;
    names.sort_by_key(|e| e.file_name());
    for entry in names {
        let name = entry.file_name().to_string_lossy().into_owned();
        let path = if rel.is_empty() {
            name.clone()
        } else {
            format!("{rel}/{name}")
        };
        let kind = entry.file_type().map_err(|e| Error::io(entry.path(), e))?;
        if (rel.is_empty() && name == OWNED_FILE && kind.is_file()) || is_debris(&name) {
            continue;
        }
        let sub = format!("{path}/");
        let found = if kind.is_dir() && record.entries.contains(&sub) {
            foreign_entry(&entry.path())?
                .map(|inner| format!("has a sub-folder {sub} that {inner}"))
        } else if kind.is_dir() && record.entries.iter().any(|e| e.starts_with(&sub)) {
            walk_foreign(root, &path, record)?
        } else if kind.is_file() && record.entries.contains(&path) {
            None
        } else if kind.is_dir() {
            Some(format!("holds {sub}, which psscan did not write"))
        } else {
            Some(format!("holds {path}, which psscan did not write"))
        };
        if found.is_some() {
            return Ok(found);
        }
    }
    Ok(None)
}

/// Whether `name` is what an interrupted psscan run leaves: a temporary file
/// (`x.tmp-PID-N`), a staged or set-aside folder (`x.partial-PID-N`, `x.old-PID-N`), a
/// capture's scratch shot (`.x.shot`).
fn is_debris(name: &str) -> bool {
    staging_owner(name).is_some() || (name.starts_with('.') && name.ends_with(".shot"))
}

/// The process id in a staging name `x.KIND-PID-N` (KIND tmp, partial or old).
fn staging_owner(name: &str) -> Option<u32> {
    let (stem, n) = name.rsplit_once('-')?;
    let (stem, pid) = stem.rsplit_once('-')?;
    let kind = stem.rsplit_once('.')?.1;
    if !matches!(kind, "tmp" | "partial" | "old") || !n.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    pid.parse().ok().filter(|_| !n.is_empty())
}

/// Whether process `pid` still runs (signal 0 probes without sending anything).
fn process_alive(pid: u32) -> bool {
    if pid == std::process::id() {
        return true;
    }
    let Ok(pid) = libc::pid_t::try_from(pid) else {
        return false;
    };
    // SAFETY: kill with signal 0 only checks that the process exists.
    let rc = unsafe { libc::kill(pid, 0) };
    rc == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// Removes staging beside `target` (`NAME.partial-PID-N`, `NAME.old-PID-N`,
/// `NAME.tmp-PID-N`) left by a psscan process that no longer runs (killed before it could
/// clean up), saying on stderr what it removed; staging it cannot remove is named instead.
pub fn remove_stale_staging(target: &Path) {
    let Some(name) = target.file_name().map(|n| n.to_string_lossy().into_owned()) else {
        return;
    };
    let parent = match target.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let Ok(entries) = fs::read_dir(parent) else {
        return;
    };
    for entry in entries.flatten() {
        let sibling = entry.file_name().to_string_lossy().into_owned();
        let Some(rest) = sibling
            .strip_prefix(&name)
            .and_then(|r| r.strip_prefix('.'))
        else {
            continue;
        };
        let kind = rest.split('-').next().unwrap_or_default();
        let Some(pid) = staging_owner(&sibling).filter(|_| rest.split('-').count() == 3) else {
            continue;
        };
        if !matches!(kind, "tmp" | "partial" | "old") {
            continue;
        }
        if process_alive(pid) {
            continue;
        }
        let path = entry.path();
        let removed = match entry.file_type() {
            Ok(t) if t.is_dir() => fs::remove_dir_all(&path).is_ok(),
            Ok(_) => fs::remove_file(&path).is_ok(),
            Err(_) => false,
        };
        if removed {
            eprintln!(
                "psscan: removed {}, left unfinished by psscan process {pid}, which no longer runs",
                path.display()
            );
        } else {
            eprintln!(
                "psscan: {} was left unfinished by psscan process {pid}, which no longer runs; \
                 it could not be removed: remove it by hand",
                path.display()
            );
        }
    }
}

/// `path` made absolute with every link resolved, also where its tail does not exist yet
/// (the nearest existing ancestor is resolved, the rest appended).
fn resolved(path: &Path) -> PathBuf {
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let mut normal = PathBuf::new();
    for part in absolute.components() {
        match part {
            Component::ParentDir => {
                normal.pop();
            }
            Component::CurDir => {}
            other => normal.push(other),
        }
    }
    let mut tail = Vec::new();
    let mut head = normal.as_path();
    loop {
        if let Ok(real) = head.canonicalize() {
            return tail.iter().rev().fold(real, |p: PathBuf, t| p.join(t));
        }
        match (head.parent(), head.file_name()) {
            (Some(parent), Some(name)) => {
                tail.push(name.to_os_string());
                head = parent;
            }
            _ => return normal,
        }
    }
}

/// Refuses an output `target` that is, holds or sits inside one of `inputs` (canonical paths
/// compared, so links and `..` do not hide it): psscan never writes into or over its inputs.
pub fn check_outside_inputs(target: &Path, inputs: &[&Path]) -> Result<()> {
    let out = resolved(target);
    for input in inputs {
        let input_path = resolved(input);
        let why = if out == input_path {
            "is an input of this run"
        } else if input_path.starts_with(&out) {
            "holds an input of this run"
        } else if out.starts_with(&input_path) {
            "sits inside an input of this run"
        } else {
            continue;
        };
        return Err(Error::Invalid(format!(
            "output folder {} {why} ({}); psscan never writes into or over its inputs, so \
             nothing was written or removed: choose an output folder outside every input",
            target.display(),
            input.display()
        )));
    }
    Ok(())
}

/// Whether the output folder `target` may be written: it does not exist, is empty, or holds
/// only what psscan wrote there (its ownership record lists every entry) and `force` allows
/// replacing it; and it is not, holds not and sits not inside any of `inputs`. Otherwise the
/// error says why, and nothing has been touched.
pub fn check_replaceable(target: &Path, force: bool, inputs: &[&Path]) -> Result<()> {
    check_outside_inputs(target, inputs)?;
    let meta = match fs::symlink_metadata(target) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(Error::io(target, e)),
        Ok(meta) => meta,
    };
    if !meta.is_dir() {
        return Err(Error::image(
            target,
            "exists and is not a folder; psscan will not replace it (choose another output \
             folder)",
        ));
    }
    let mut entries = fs::read_dir(target).map_err(|e| Error::io(target, e))?;
    if entries.next().is_none() {
        return Ok(());
    }
    if let Some(why) = foreign_entry(target)? {
        return Err(Error::image(
            target,
            format!(
                "is not empty and {why}; psscan replaces only a folder every entry of which it \
                 wrote, so nothing was removed (choose another output folder)"
            ),
        ));
    }
    if !force {
        return Err(Error::Exists {
            path: target.to_path_buf(),
        });
    }
    Ok(())
}

/// Makes `target` a fresh, empty output folder of this run, as [`check_replaceable`] allows:
/// an old psscan output there is removed (with `force`), and the folder's ownership record
/// lists `entries` (sub-folders this writer will fill, as `name/`). Claiming the same folder
/// again in this run keeps what the run has written there since.
pub fn claim_dir(target: &Path, force: bool, inputs: &[&Path], entries: &[&str]) -> Result<()> {
    let key = resolved(target);
    let claimed = CLAIMED
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .contains(&key);
    if !claimed {
        check_replaceable(target, force, inputs)?;
        remove_stale_staging(target);
        if target.exists() {
            let old = temp_sibling_with(target, "old");
            register(&old);
            fs::rename(target, &old).map_err(|e| Error::io(target, e))?;
            let _ = fs::remove_dir_all(&old);
            unregister(&old);
        }
        create_dir_all(target)?;
        CLAIMED.lock().unwrap_or_else(|e| e.into_inner()).push(key);
    }
    record_owned(target, entries.iter().copied())
}

/// An output folder built under a temporary name beside its final one and renamed into place
/// when complete, so the final name only ever holds a whole output. What it may replace is
/// [`check_replaceable`]'s rule; the ownership record of every entry is written on commit.
pub struct StagedDir {
    target: PathBuf,
    temp: PathBuf,
    committed: bool,
}

impl StagedDir {
    /// Starts staging the output `target`: checks it may be written (see
    /// [`check_replaceable`]), removes staging a killed psscan left beside it, and creates the
    /// temporary folder.
    pub fn create(target: &Path, force: bool, inputs: &[&Path]) -> Result<StagedDir> {
        check_replaceable(target, force, inputs)?;
        if let Some(parent) = target.parent().filter(|p| !p.as_os_str().is_empty()) {
            create_dir_all(parent)?;
        }
        remove_stale_staging(target);
        let temp = temp_sibling_with(target, "partial");
        register(&temp);
        if let Err(e) = fs::create_dir(&temp) {
            unregister(&temp);
            return Err(Error::io(&temp, e));
        }
        Ok(StagedDir {
            target: target.to_path_buf(),
            temp,
            committed: false,
        })
    }

    /// Where to write the output while it is being built.
    pub fn path(&self) -> &Path {
        &self.temp
    }

    /// The name the output will have.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// Records what was written, then renames the finished output into place (replacing an
    /// old one, which was checked when the stage was created and is checked again now).
    pub fn commit(mut self, force: bool, inputs: &[&Path]) -> Result<()> {
        record_owned(&self.temp, entries_of_tree(&self.temp)?)?;
        check_replaceable(&self.target, force, inputs)?;
        // The registry is held across the renames: a signal handler waits for them, so it
        // never finds the old output set aside and the new one not yet in place.
        let mut list = staging();
        let old = if self.target.exists() {
            let old = temp_sibling_with(&self.target, "old");
            fs::rename(&self.target, &old).map_err(|e| Error::io(&self.target, e))?;
            Some(old)
        } else {
            None
        };
        if let Err(e) = fs::rename(&self.temp, &self.target) {
            if let Some(old) = &old {
                let _ = fs::rename(old, &self.target);
            }
            return Err(Error::io(&self.target, e));
        }
        self.committed = true;
        list.retain(|p| p != &self.temp);
        if let Some(old) = &old {
            list.push(old.clone());
        }
        // Recorded before the registry is let go: a signal handler that got it after the
        // renames finds the output here.
        COMMITTED
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(CommittedOutput {
                path: self.target.clone(),
                replaced: old.clone(),
            });
        drop(list);
        if let Some(old) = old {
            let _ = fs::remove_dir_all(&old);
            unregister(&old);
        }
        Ok(())
    }
}

impl Drop for StagedDir {
    /// An output that failed half-way is removed; the final name never saw it.
    fn drop(&mut self) {
        if !self.committed {
            let _ = fs::remove_dir_all(&self.temp);
            unregister(&self.temp);
        }
    }
}

fn temp_sibling_with(path: &Path, kind: &str) -> PathBuf {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let name = path
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    path.with_file_name(format!("{name}.{kind}-{}-{n}", std::process::id()))
}

#[cfg(test)]
mod tests;
