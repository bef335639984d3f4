//! File-system helpers shared by every writer: atomic writes (so a crash never leaves a
//! half-written file under its final name) and SHA-256 of files.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use crate::error::{Error, Result};

/// Writes `bytes` to `path` through a temporary file in the same folder, flushed to disk and
/// then renamed over the destination. Readers see either the old file or the whole new one.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = temp_sibling(path);
    let result = (|| -> std::io::Result<()> {
        let mut file = fs::File::create(&tmp)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        fs::rename(&tmp, path)
    })();
    if let Err(source) = result {
        let _ = fs::remove_file(&tmp);
        return Err(Error::io(path, source));
    }
    Ok(())
}

/// A name beside `path` that no other writer uses: `name.tmp-<pid>-<n>`.
fn temp_sibling(path: &Path) -> PathBuf {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let name = path
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    path.with_file_name(format!("{name}.tmp-{}-{n}", std::process::id()))
}

/// Lower-case hex SHA-256 of a byte slice.
pub fn sha256_hex(bytes: &[u8]) -> String {
    let digest = Sha256::digest(bytes);
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

/// An output folder built under a temporary name beside its final one and renamed into place
/// when complete, so the final name only ever holds a whole output. An existing output is
/// replaced only with `force`, and only when it holds `marker` (proof that psscan wrote it) or
/// is empty: a folder of someone else's files is never replaced.
pub struct StagedDir {
    target: PathBuf,
    temp: PathBuf,
    committed: bool,
}

impl StagedDir {
    pub fn create(target: &Path, force: bool, marker: &str) -> Result<StagedDir> {
        check_replaceable(target, force, marker)?;
        if let Some(parent) = target.parent().filter(|p| !p.as_os_str().is_empty()) {
            create_dir_all(parent)?;
        }
        let temp = temp_sibling_with(target, "partial");
        fs::create_dir(&temp).map_err(|e| Error::io(&temp, e))?;
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

    /// Renames the finished output into place (replacing an old one, which was checked when
    /// the stage was created and is checked again now).
    pub fn commit(mut self, force: bool, marker: &str) -> Result<()> {
        check_replaceable(&self.target, force, marker)?;
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
        if let Some(old) = old {
            let _ = fs::remove_dir_all(old);
        }
        Ok(())
    }
}

impl Drop for StagedDir {
    /// An output that failed half-way is removed; the final name never saw it.
    fn drop(&mut self) {
        if !self.committed {
            let _ = fs::remove_dir_all(&self.temp);
        }
    }
}

fn check_replaceable(target: &Path, force: bool, marker: &str) -> Result<()> {
    let meta = match fs::symlink_metadata(target) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(Error::io(target, e)),
        Ok(meta) => meta,
    };
    if !meta.is_dir() {
        return Err(Error::image(
            target,
            "exists and is not a folder; choose another output folder",
        ));
    }
    let mut entries = fs::read_dir(target).map_err(|e| Error::io(target, e))?;
    if entries.next().is_none() {
        return Ok(());
    }
    if !target.join(marker).is_file() {
        return Err(Error::image(
            target,
            format!(
                "is not empty and holds no {marker}, so it is not a psscan output; psscan \
                 will not replace it (choose another output folder)"
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
mod tests {
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
        let stage = StagedDir::create(&out, false, "report.json").unwrap();
        fs::write(stage.path().join("normal.png"), b"half").unwrap();
        drop(stage);
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 0);

        let stage = StagedDir::create(&out, false, "report.json").unwrap();
        fs::write(stage.path().join("report.json"), b"1").unwrap();
        stage.commit(false, "report.json").unwrap();
        assert_eq!(fs::read(out.join("report.json")).unwrap(), b"1");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);

        // An existing output needs force, and is then replaced as a whole.
        let err = StagedDir::create(&out, false, "report.json").err().unwrap();
        assert!(err.to_string().contains("--force"), "{err}");
        let stage = StagedDir::create(&out, true, "report.json").unwrap();
        fs::write(stage.path().join("report.json"), b"2").unwrap();
        stage.commit(true, "report.json").unwrap();
        assert_eq!(fs::read(out.join("report.json")).unwrap(), b"2");
        assert_eq!(fs::read_dir(&out).unwrap().count(), 1);
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_folder_of_other_files_is_never_replaced() {
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join("thesis.tex"), b"precious").unwrap();
        let err = StagedDir::create(dir.path(), true, "report.json")
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("not a psscan output"), "{err}");
        // An empty folder is fine.
        let empty = dir.path().join("empty");
        fs::create_dir(&empty).unwrap();
        assert!(StagedDir::create(&empty, false, "report.json").is_ok());
    }

    #[test]
    fn sha256_of_known_input() {
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }
}
