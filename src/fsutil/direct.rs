//! A file written past the page cache (Linux `O_DIRECT`), for the large map files a solve
//! writes once, flushes to disk and does not read back.
//!
//! Why: a buffered write copies every byte into page-cache pages the kernel must first take
//! and clear, and a 16 MP solve writes 850 MB of maps. On the development VM the kernel's copy
//! (`copy_folio_from_iter_atomic`) was the largest single item in one `perf` profile of a
//! 16 MP solve, 14 % of its samples (0.55 % in another: it depends on the memory's state);
//! `dd` of 800 MB with `conv=fsync` took 0.24-1.93 s of system time buffered against
//! 0.10-0.19 s with `oflag=direct` (5 runs each).
//!
//! How: the encoder's bytes are gathered into aligned blocks, and each full block is written
//! by a thread of the file's own while the encoder fills the next (a few blocks are reused, so
//! the writes take no new memory). A write before the block being filled (an EXR's offset
//! table, filled in last) is kept aside and written, buffered, when the file is finished; the
//! last block is written padded and the file cut to its length. Where the file system refuses
//! direct writes (at open or at the first write) the same blocks are written buffered.

use std::fs::File;
use std::io::{Error, ErrorKind, Result, Seek, SeekFrom, Write};
use std::path::Path;
use std::sync::mpsc::{channel, sync_channel, Receiver, Sender, SyncSender};
use std::thread::JoinHandle;

/// The alignment of a direct write's offset, length and memory: a multiple of every logical
/// block size Linux devices use (512 or 4096 bytes).
const ALIGN: usize = 4096;

/// The size of the blocks written: large enough that each write costs little beside the
/// device's time, small enough that the few in flight take little memory.
pub const BLOCK: usize = 2 << 20;

/// The most blocks one file holds at once: one being filled, one queued, one being written.
const BLOCKS_IN_FLIGHT: usize = 3;

/// A buffer of `len` bytes whose start is aligned to [`ALIGN`] (a slice of a longer vector,
/// so no unsafe allocation is needed).
struct AlignedBlock {
    bytes: Vec<u8>,
    start: usize,
    len: usize,
}

impl AlignedBlock {
    fn new(len: usize) -> AlignedBlock {
        let bytes = vec![0u8; len + ALIGN];
        let start = bytes.as_ptr().align_offset(ALIGN);
        AlignedBlock { bytes, start, len }
    }

    fn as_slice(&self) -> &[u8] {
        &self.bytes[self.start..self.start + self.len]
    }

    fn as_mut_slice(&mut self) -> &mut [u8] {
        &mut self.bytes[self.start..self.start + self.len]
    }
}

/// A block handed to the writing thread: the file offset it starts at, and how many of its
/// bytes to write (a multiple of [`ALIGN`]).
struct Submitted {
    offset: u64,
    block: AlignedBlock,
    len: usize,
}

/// The thread that writes a file's blocks, and the blocks it hands back for reuse.
struct BlockWriter {
    queue: SyncSender<Submitted>,
    returned: Receiver<AlignedBlock>,
    thread: JoinHandle<Result<()>>,
}

/// A `Write + Seek` file whose bytes bypass the page cache where the file system allows it
/// (see the module's notes). [`DirectFile::finish`] must be called to write its last bytes.
pub struct DirectFile {
    file: File,
    block_size: usize,
    /// The block being filled; it holds the file's bytes from `block_start`.
    block: AlignedBlock,
    block_start: u64,
    /// How many of the block's bytes have been written (they are contiguous from its start).
    block_filled: usize,
    blocks_made: usize,
    /// Writes before `block_start` (already handed to the writer), written last.
    patches: Vec<(u64, Vec<u8>)>,
    /// The encoder's position, and the file's length (the furthest byte written).
    position: u64,
    end: u64,
    writer: Option<BlockWriter>,
}

impl DirectFile {
    /// Creates (or truncates) `path` for direct writes, in blocks of [`BLOCK`] bytes.
    pub fn create(path: &Path) -> Result<DirectFile> {
        DirectFile::with_block_size(path, BLOCK)
    }

    /// [`DirectFile::create`] with blocks of `block_size` bytes (a multiple of 4096; tests
    /// use small ones to cross many block boundaries).
    pub fn with_block_size(path: &Path, block_size: usize) -> Result<DirectFile> {
        assert!(block_size > 0 && block_size % ALIGN == 0);
        let file = open_direct(path)?;
        let writer = spawn_block_writer(file.try_clone()?)?;
        Ok(DirectFile {
            file,
            block_size,
            block: AlignedBlock::new(block_size),
            block_start: 0,
            block_filled: 0,
            blocks_made: 1,
            patches: Vec::new(),
            position: 0,
            end: 0,
            writer: Some(writer),
        })
    }

    /// Writes what is left (the last block, padded, then the patches), cuts the file to its
    /// length and returns it, not yet flushed to disk. A failed block write is reported here
    /// if no write reported it before.
    pub fn finish(mut self) -> Result<File> {
        if self.block_filled > 0 {
            let padded = self.block_filled.next_multiple_of(ALIGN);
            self.block.as_mut_slice()[self.block_filled..padded].fill(0);
            let block = std::mem::replace(&mut self.block, AlignedBlock::new(0));
            self.send(block, padded)?;
        }
        let writer = self.writer.take().expect("finished once");
        drop(writer.queue);
        join(writer.thread)?;
        self.file.set_len(self.end)?;
        if !self.patches.is_empty() {
            // Small and out of order: written through the page cache.
            stop_direct(&self.file)?;
            for (offset, bytes) in &self.patches {
                write_all_at(&self.file, bytes, *offset)?;
            }
        }
        // A handle of its own: `self` (which has a `Drop`) closes the one it holds.
        self.file.try_clone()
    }

    /// Hands the full block to the writer and starts the next one.
    fn submit_block(&mut self) -> Result<()> {
        let next = self.spare_block()?;
        let full = std::mem::replace(&mut self.block, next);
        self.send(full, self.block_size)?;
        self.block_start += self.block_size as u64;
        self.block_filled = 0;
        Ok(())
    }

    fn send(&mut self, block: AlignedBlock, len: usize) -> Result<()> {
        let offset = self.block_start;
        let writer = self.writer.as_ref().expect("not finished");
        if writer.queue.send(Submitted { offset, block, len }).is_err() {
            return Err(self.writer_error());
        }
        Ok(())
    }

    /// A block the writer has handed back, or a new one while fewer than
    /// [`BLOCKS_IN_FLIGHT`] exist.
    fn spare_block(&mut self) -> Result<AlignedBlock> {
        let writer = self.writer.as_ref().expect("not finished");
        if let Ok(block) = writer.returned.try_recv() {
            return Ok(block);
        }
        if self.blocks_made < BLOCKS_IN_FLIGHT {
            self.blocks_made += 1;
            return Ok(AlignedBlock::new(self.block_size));
        }
        match writer.returned.recv() {
            Ok(block) => Ok(block),
            Err(_) => Err(self.writer_error()),
        }
    }

    /// The error the writing thread stopped on (it stops only on one).
    fn writer_error(&mut self) -> Error {
        let writer = self.writer.take().expect("not finished");
        drop(writer.queue);
        match join(writer.thread) {
            Err(e) => e,
            Ok(()) => Error::other("the block writer stopped"),
        }
    }
}

impl Write for DirectFile {
    fn write(&mut self, bytes: &[u8]) -> Result<usize> {
        if bytes.is_empty() {
            return Ok(0);
        }
        if self.writer.is_none() {
            return Err(Error::other("a block write failed before"));
        }
        let written = if self.position < self.block_start {
            let n = bytes.len().min((self.block_start - self.position) as usize);
            self.patches.push((self.position, bytes[..n].to_vec()));
            n
        } else {
            let at = (self.position - self.block_start) as usize;
            if at >= self.block_size {
                // A seek past the block: the gap is zeros.
                self.block.as_mut_slice()[self.block_filled..].fill(0);
                self.submit_block()?;
                return self.write(bytes);
            }
            let n = bytes.len().min(self.block_size - at);
            let block = self.block.as_mut_slice();
            if at > self.block_filled {
                block[self.block_filled..at].fill(0);
            }
            block[at..at + n].copy_from_slice(&bytes[..n]);
            self.block_filled = self.block_filled.max(at + n);
            if self.block_filled == self.block_size {
                self.submit_block()?;
            }
            n
        };
        self.position += written as u64;
        self.end = self.end.max(self.position);
        Ok(written)
    }

    /// Nothing to do: a block is written when it is full, the last one by `finish`.
    fn flush(&mut self) -> Result<()> {
        Ok(())
    }
}

impl Seek for DirectFile {
    fn seek(&mut self, to: SeekFrom) -> Result<u64> {
        let target = match to {
            SeekFrom::Start(p) => Some(p),
            SeekFrom::Current(d) => self.position.checked_add_signed(d),
            SeekFrom::End(d) => self.end.checked_add_signed(d),
        };
        self.position = target
            .ok_or_else(|| Error::new(ErrorKind::InvalidInput, "a seek before the file's start"))?;
        Ok(self.position)
    }
}

impl Drop for DirectFile {
    fn drop(&mut self) {
        // Unfinished (an encoder failed): stop the writer; the caller removes the file.
        if let Some(writer) = self.writer.take() {
            drop(writer.queue);
            let _ = writer.thread.join();
        }
    }
}

fn spawn_block_writer(file: File) -> Result<BlockWriter> {
    let (queue, blocks) = sync_channel::<Submitted>(1);
    let (give_back, returned) = channel();
    let thread = std::thread::Builder::new()
        .name("psscan-file-writer".into())
        .spawn(move || write_blocks(&file, blocks, give_back))?;
    Ok(BlockWriter {
        queue,
        returned,
        thread,
    })
}

/// The writing thread: each block at its offset, until the queue closes or a write fails.
fn write_blocks(
    file: &File,
    blocks: Receiver<Submitted>,
    give_back: Sender<AlignedBlock>,
) -> Result<()> {
    for Submitted { offset, block, len } in blocks {
        let bytes = &block.as_slice()[..len];
        match write_all_at(file, bytes, offset) {
            // A file system that takes the flag at open but not the writes: buffered.
            Err(e) if e.kind() == ErrorKind::InvalidInput => {
                stop_direct(file)?;
                write_all_at(file, bytes, offset)?;
            }
            other => other?,
        }
        // The encoder may have finished and stopped listening: nothing to hand back to.
        let _ = give_back.send(block);
    }
    Ok(())
}

fn join(thread: JoinHandle<Result<()>>) -> Result<()> {
    thread
        .join()
        .unwrap_or_else(|_| Err(Error::other("the block writer panicked")))
}

#[cfg(unix)]
fn write_all_at(file: &File, bytes: &[u8], offset: u64) -> Result<()> {
    std::os::unix::fs::FileExt::write_all_at(file, bytes, offset)
}

#[cfg(not(unix))]
fn write_all_at(file: &File, bytes: &[u8], offset: u64) -> Result<()> {
    let mut file = file;
    file.seek(SeekFrom::Start(offset))?;
    file.write_all(bytes)
}

/// Opens `path` for writing (created or truncated) with `O_DIRECT` where the file system
/// takes it, else without.
#[cfg(target_os = "linux")]
fn open_direct(path: &Path) -> Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    let direct = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .custom_flags(libc::O_DIRECT)
        .open(path);
    match direct {
        Err(e) if e.kind() == ErrorKind::InvalidInput => File::create(path),
        other => other,
    }
}

#[cfg(not(target_os = "linux"))]
fn open_direct(path: &Path) -> Result<File> {
    File::create(path)
}

/// Turns `O_DIRECT` off for `file` (and every handle sharing its open file).
#[cfg(target_os = "linux")]
fn stop_direct(file: &File) -> Result<()> {
    use std::os::unix::io::AsRawFd;
    let fd = file.as_raw_fd();
    // SAFETY: fcntl on a descriptor this process owns, with flags it read from it.
    let flags = unsafe { libc::fcntl(fd, libc::F_GETFL) };
    if flags < 0 {
        return Err(Error::last_os_error());
    }
    // SAFETY: as above.
    if unsafe { libc::fcntl(fd, libc::F_SETFL, flags & !libc::O_DIRECT) } < 0 {
        return Err(Error::last_os_error());
    }
    Ok(())
}

#[cfg(not(target_os = "linux"))]
fn stop_direct(_file: &File) -> Result<()> {
    Ok(())
}
