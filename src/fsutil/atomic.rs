//! Files written whole or not at all: through a temporary sibling, flushed to disk, then
//! renamed over the destination (registered as staging meanwhile, so an interrupt removes it).

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use super::{register, temp_sibling, unregister};
use crate::error::{Error, Result};

/// Writes `bytes` to `path` through a temporary file in the same folder, flushed to disk and
/// then renamed over the destination. Readers see either the old file or the whole new one.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut file = AtomicFile::create(path)?;
    // Dropped uncommitted on a failed write: the temporary file is removed.
    file.writer()
        .write_all(bytes)
        .map_err(|e| Error::io(path, e))?;
    file.commit()
}

/// A file written in place of `path` the way [`write_atomic`] writes one, for an encoder that
/// streams into it (a 16 MP map's file bytes need not sit in memory first): its bytes go to a
/// temporary sibling, and [`AtomicFile::commit`] flushes them to disk and renames it over
/// `path`. Dropped without a commit (an encoder failed), the temporary file is removed.
pub struct AtomicFile {
    path: PathBuf,
    tmp: PathBuf,
    file: Option<std::io::BufWriter<fs::File>>,
}

/// The buffer between an encoder and its file: large enough that the write calls cost
/// nothing beside the encoding.
const ATOMIC_FILE_BUFFER: usize = 1 << 20;

impl AtomicFile {
    /// Creates the temporary sibling of `path` (registered as staging, so an interrupt
    /// removes it).
    pub fn create(path: &Path) -> Result<AtomicFile> {
        let tmp = temp_sibling(path);
        register(&tmp);
        match fs::File::create(&tmp) {
            Ok(file) => Ok(AtomicFile {
                path: path.to_path_buf(),
                tmp,
                file: Some(std::io::BufWriter::with_capacity(ATOMIC_FILE_BUFFER, file)),
            }),
            Err(source) => {
                unregister(&tmp);
                Err(Error::io(path, source))
            }
        }
    }

    /// Where the encoder writes (buffered; seekable for formats that go back to fill in an
    /// offset table).
    pub fn writer(&mut self) -> &mut std::io::BufWriter<fs::File> {
        self.file.as_mut().expect("a file not yet committed")
    }

    /// Flushes what was written to disk and renames the file over its final path.
    pub fn commit(mut self) -> Result<()> {
        let file = self.file.take().expect("committed once");
        let result = (|| -> std::io::Result<()> {
            let file = file.into_inner().map_err(|e| e.into_error())?;
            file.sync_all()?;
            fs::rename(&self.tmp, &self.path)
        })();
        if let Err(source) = result {
            let _ = fs::remove_file(&self.tmp);
            unregister(&self.tmp);
            return Err(Error::io(&self.path, source));
        }
        unregister(&self.tmp);
        Ok(())
    }
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        if self.file.take().is_some() {
            let _ = fs::remove_file(&self.tmp);
            unregister(&self.tmp);
        }
    }
}
