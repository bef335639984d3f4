//! Reading a frame file while hashing it (the manifest's SHA-256 check): whole, or as a
//! decoder reads it.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use super::{checked_inside, CaptureSet};
use crate::capture::manifest::FrameEntry;
use crate::error::{Error, Result};
use crate::raw::{decode_codec, Coded, Encoding, DN16_DECODE_STAGE};
use crate::timing::Busy;

/// Reads `path` whole into `bytes` (emptied first; its memory is reused), hashing each chunk
/// as it arrives (a chunk is hashed while it is still in the CPU's cache, not in a second pass
/// over the whole file); the read and the hash time go to `busy`'s [`READ_STAGE`] and
/// [`HASH_STAGE`].
pub(super) fn read_and_hash(
    path: &Path,
    busy: &Busy,
    mut bytes: Vec<u8>,
) -> Result<(Vec<u8>, String)> {
    use sha2::{Digest, Sha256};
    use std::io::Read;
    const CHUNK: usize = 1 << 20;
    let start = Instant::now();
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = file.metadata().map(|m| m.len() as usize).unwrap_or(0);
    bytes.clear();
    bytes.reserve(len + 1);
    let mut hasher = Sha256::new();
    let mut hashing = Duration::ZERO;
    loop {
        let done = bytes.len();
        let n = (&mut file)
            .take(CHUNK as u64)
            .read_to_end(&mut bytes)
            .map_err(|e| Error::io(path, e))?;
        if n == 0 {
            break;
        }
        let t = Instant::now();
        hasher.update(&bytes[done..]);
        hashing += t.elapsed();
    }
    let t = Instant::now();
    let digest = crate::fsutil::hex(&hasher.finalize());
    hashing += t.elapsed();
    busy.add(HASH_STAGE, hashing);
    busy.add(READ_STAGE, start.elapsed().saturating_sub(hashing));
    Ok((bytes, digest))
}

/// Stage names of loading a set's frames.
pub const READ_STAGE: &str = "read";
pub const HASH_STAGE: &str = "hash check";

/// A frame file read in order through its SHA-256: what a decoder reads or consumes is hashed
/// as it passes (a dn16 frame is decoded as it is read, with no whole-file buffer: the first
/// frames' buffers were 80 MB each of fresh memory at 16 MP, a page fault and the kernel's
/// zeroing per page). The time spent reading and hashing is kept apart from the decoder's.
pub(super) struct HashingReader {
    file: std::io::BufReader<std::fs::File>,
    hasher: sha2::Sha256,
    /// False once the reader was asked to seek anywhere but where it is: the hash is then
    /// not of the file in order, and [`HashingReader::finish`] gives none.
    in_order: bool,
    reading: Duration,
    hashing: Duration,
}

/// Bytes read from the file at a time.
const STREAM_BUFFER: usize = 256 << 10;

impl HashingReader {
    /// Opens `path`.
    pub(super) fn open(path: &Path) -> Result<Self> {
        use sha2::Digest;
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        Ok(HashingReader {
            file: std::io::BufReader::with_capacity(STREAM_BUFFER, file),
            hasher: sha2::Sha256::new(),
            in_order: true,
            reading: Duration::ZERO,
            hashing: Duration::ZERO,
        })
    }

    /// Reads the rest of the file through the hash (a decoder stops at the image's end) and
    /// returns the file's SHA-256 in hex, `None` where the reader did not read it in order;
    /// the read and hash time go to `busy`'s [`READ_STAGE`] and [`HASH_STAGE`].
    pub(super) fn finish(mut self, path: &Path, busy: &Busy) -> Result<Option<String>> {
        use sha2::Digest;
        use std::io::BufRead;
        loop {
            let n = std::io::BufRead::fill_buf(&mut self)
                .map_err(|e| Error::io(path, e))?
                .len();
            if n == 0 {
                break;
            }
            self.consume(n);
        }
        self.record(busy);
        Ok(self
            .in_order
            .then(|| crate::fsutil::hex(&self.hasher.finalize())))
    }

    /// The time spent reading and hashing so far.
    pub(super) fn own_time(&self) -> Duration {
        self.reading + self.hashing
    }

    /// Adds the read and hash time so far to `busy`'s [`READ_STAGE`] and [`HASH_STAGE`].
    pub(super) fn record(&self, busy: &Busy) {
        busy.add(READ_STAGE, self.reading);
        busy.add(HASH_STAGE, self.hashing);
    }
}

impl std::io::Read for HashingReader {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let t = Instant::now();
        let n = self.file.read(buf)?;
        self.reading += t.elapsed();
        let t = Instant::now();
        sha2::Digest::update(&mut self.hasher, &buf[..n]);
        self.hashing += t.elapsed();
        Ok(n)
    }
}

impl std::io::BufRead for HashingReader {
    fn fill_buf(&mut self) -> std::io::Result<&[u8]> {
        let t = Instant::now();
        self.file.fill_buf()?;
        self.reading += t.elapsed();
        Ok(self.file.buffer())
    }

    fn consume(&mut self, amount: usize) {
        // Hashed as consumed: what `fill_buf` shows may be shown again before it is used.
        use sha2::Digest;
        let t = Instant::now();
        self.hasher.update(&self.file.buffer()[..amount]);
        self.hashing += t.elapsed();
        self.file.consume(amount);
    }
}

impl std::io::Seek for HashingReader {
    fn seek(&mut self, pos: std::io::SeekFrom) -> std::io::Result<u64> {
        if pos != std::io::SeekFrom::Current(0) {
            self.in_order = false;
        }
        self.file.seek(pos)
    }
}

impl CaptureSet {
    /// [`Self::read_frame_bytes`] into `buffer`, hashing while reading, the time of each going
    /// to `busy`.
    pub(super) fn read_frame_bytes_timed(
        &self,
        entry: &FrameEntry,
        busy: &Busy,
        buffer: Vec<u8>,
    ) -> Result<(PathBuf, Vec<u8>)> {
        let path = checked_inside(&self.dir, &entry.file)?;
        let (bytes, actual) = read_and_hash(&path, busy, buffer)?;
        check_hash(&path, entry, &actual)?;
        Ok((path, bytes))
    }

    /// Decodes a dn16 frame as it is read and hashed (no whole-file buffer, see
    /// [`HashingReader`]); the hash is checked before the decode's outcome is looked at, so a
    /// changed file is named as such even where it also fails to decode. A frame that is not a
    /// plain 16-bit RGB PNG (a TIFF) is read whole and decoded the long way, which checks the
    /// hash first too: the stream is left where the PNG decoder gave up, not read on to hash.
    pub(super) fn decode_dn16_streamed(
        &self,
        entry: &FrameEntry,
        levels: &crate::raw::Levels,
        busy: &Busy,
    ) -> Result<(PathBuf, Coded)> {
        let path = checked_inside(&self.dir, &entry.file)?;
        let mut reader = HashingReader::open(&path)?;
        let start = std::time::Instant::now();
        let decoded = crate::raw::png_rows_from(&mut reader, levels);
        busy.add(
            DN16_DECODE_STAGE,
            start.elapsed().saturating_sub(reader.own_time()),
        );
        let Some(decoded) = decoded else {
            reader.record(busy);
            let (path, bytes) = self.read_frame_bytes_timed(entry, busy, Vec::new())?;
            let (coded, _) = decode_codec(bytes, &path, Encoding::Dn16, levels, busy);
            return Ok((path, coded?));
        };
        let actual = match reader.finish(&path, busy)? {
            Some(actual) => actual,
            None => read_and_hash(&path, busy, Vec::new())?.1,
        };
        check_hash(&path, entry, &actual)?;
        let frame = decoded.map_err(|e| Error::image(&path, e))?;
        Ok((path, Coded::dn16(frame, levels)))
    }
}

/// Fails naming `path` where its SHA-256 (`actual`) is not the one `entry` recorded.
fn check_hash(path: &Path, entry: &FrameEntry, actual: &str) -> Result<()> {
    if actual == entry.sha256 {
        return Ok(());
    }
    Err(Error::image(
        path,
        format!(
            "SHA-256 mismatch: manifest says {}, file is {actual}; the file was changed or \
             damaged after capture",
            entry.sha256
        ),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{BufRead, Read, Seek, SeekFrom};

    /// A file's bytes, read by a decoder's mix of `read`, `fill_buf` (the same bytes shown
    /// twice) and `consume`, and left unread past some point: the hash is the whole file's.
    #[test]
    fn the_streamed_hash_is_the_files_however_it_is_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frame.png");
        let bytes: Vec<u8> = (0..3 * STREAM_BUFFER + 1234)
            .map(|i| (i * 31 % 251) as u8)
            .collect();
        std::fs::write(&path, &bytes).unwrap();
        let whole = crate::fsutil::sha256_hex(&bytes);
        let mut reader = HashingReader::open(&path).unwrap();
        let mut head = [0u8; 1000];
        reader.read_exact(&mut head).unwrap();
        assert_eq!(&head[..], &bytes[..1000]);
        let shown = reader.fill_buf().unwrap().to_vec();
        assert_eq!(reader.fill_buf().unwrap(), &shown[..]);
        reader.consume(shown.len() / 2);
        assert_eq!(
            reader.stream_position().unwrap(),
            (1000 + shown.len() / 2) as u64
        );
        let mut big = vec![0u8; 2 * STREAM_BUFFER];
        reader.read_exact(&mut big).unwrap();
        let start = 1000 + shown.len() / 2;
        assert_eq!(&big[..], &bytes[start..start + big.len()]);
        let busy = Busy::new(&[READ_STAGE, HASH_STAGE]);
        assert_eq!(reader.finish(&path, &busy).unwrap(), Some(whole));
    }

    /// A seek anywhere but where the reader is leaves no hash to trust (asking where it is
    /// seeks by nothing).
    #[test]
    fn a_seek_leaves_no_hash() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frame.png");
        std::fs::write(&path, vec![7u8; 5000]).unwrap();
        let busy = Busy::new(&[READ_STAGE, HASH_STAGE]);
        let mut reader = HashingReader::open(&path).unwrap();
        reader.stream_position().unwrap();
        let whole = crate::fsutil::sha256_hex(&[7u8; 5000]);
        assert_eq!(reader.finish(&path, &busy).unwrap(), Some(whole));
        let mut reader = HashingReader::open(&path).unwrap();
        reader.seek(SeekFrom::Start(10)).unwrap();
        assert_eq!(reader.finish(&path, &busy).unwrap(), None);
    }
}
