//! Files written whole or not at all: through a temporary sibling, flushed to disk, then
//! renamed over the destination (registered as staging meanwhile, so an interrupt removes it).

use std::fs;
use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::direct::DirectFile;
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
    file: Option<FileWriter>,
}

/// Where an [`AtomicFile`]'s bytes go: through a buffer and the page cache, or past the page
/// cache ([`DirectFile`], for large files).
pub enum FileWriter {
    /// Through a buffer of `ATOMIC_FILE_BUFFER` bytes and the page cache.
    Buffered(std::io::BufWriter<fs::File>),
    /// Past the page cache.
    Direct(DirectFile),
}

/// The buffer between an encoder and its file: large enough that the write calls cost
/// nothing beside the encoding.
const ATOMIC_FILE_BUFFER: usize = 1 << 20;

impl AtomicFile {
    /// Creates the temporary sibling of `path` (registered as staging, so an interrupt
    /// removes it).
    pub fn create(path: &Path) -> Result<AtomicFile> {
        AtomicFile::create_with(path, |tmp| {
            let file = fs::File::create(tmp)?;
            Ok(FileWriter::Buffered(std::io::BufWriter::with_capacity(
                ATOMIC_FILE_BUFFER,
                file,
            )))
        })
    }

    /// [`AtomicFile::create`] for a large file that is not read back soon (a 16 MP map): its
    /// bytes bypass the page cache where the file system allows it ([`DirectFile`]).
    pub fn create_uncached(path: &Path) -> Result<AtomicFile> {
        AtomicFile::create_with(path, |tmp| Ok(FileWriter::Direct(DirectFile::create(tmp)?)))
    }

    fn create_with(
        path: &Path,
        open: impl FnOnce(&Path) -> std::io::Result<FileWriter>,
    ) -> Result<AtomicFile> {
        let tmp = temp_sibling(path);
        register(&tmp);
        match open(&tmp) {
            Ok(file) => Ok(AtomicFile {
                path: path.to_path_buf(),
                tmp,
                file: Some(file),
            }),
            Err(source) => {
                unregister(&tmp);
                Err(Error::io(path, source))
            }
        }
    }

    /// Where the encoder writes (through a buffer or past the page cache, as created; seekable
    /// for formats that go back to fill in an offset table).
    pub fn writer(&mut self) -> &mut FileWriter {
        self.file.as_mut().expect("a file not yet committed")
    }

    /// Flushes what was written to disk and renames the file over its final path.
    pub fn commit(mut self) -> Result<()> {
        let file = self.file.take().expect("committed once");
        let result = (|| -> std::io::Result<()> {
            let file = match file {
                FileWriter::Buffered(buffered) => {
                    buffered.into_inner().map_err(|e| e.into_error())?
                }
                FileWriter::Direct(direct) => direct.finish()?,
            };
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

impl Write for FileWriter {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        match self {
            FileWriter::Buffered(w) => w.write(bytes),
            FileWriter::Direct(w) => w.write(bytes),
        }
    }

    fn write_all(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        match self {
            FileWriter::Buffered(w) => w.write_all(bytes),
            FileWriter::Direct(w) => w.write_all(bytes),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        match self {
            FileWriter::Buffered(w) => w.flush(),
            FileWriter::Direct(w) => w.flush(),
        }
    }
}

impl Seek for FileWriter {
    fn seek(&mut self, to: SeekFrom) -> std::io::Result<u64> {
        match self {
            FileWriter::Buffered(w) => w.seek(to),
            FileWriter::Direct(w) => w.seek(to),
        }
    }
}
