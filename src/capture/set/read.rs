//! Reading a frame file whole while hashing it (the manifest's SHA-256 check).

use std::path::Path;
use std::time::{Duration, Instant};

use crate::error::{Error, Result};
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
    let digest: String = hasher
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    hashing += t.elapsed();
    busy.add(HASH_STAGE, hashing);
    busy.add(READ_STAGE, start.elapsed().saturating_sub(hashing));
    Ok((bytes, digest))
}

/// Stage names of loading a set's frames.
pub const READ_STAGE: &str = "read";
pub const HASH_STAGE: &str = "hash check";
