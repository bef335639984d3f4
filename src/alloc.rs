//! Allocation helpers: the `psscan` binary's global allocator ([`LargePageAlloc`], and
//! [`keep_freed_memory`] at start), a counting one, so benchmarks can report peak heap memory
//! of one stage (installed instead when built with the `count-alloc` feature, [`COUNTING`]; the
//! library only reads the counters, zero when not installed), and the hint that backs a buffer
//! with small pages after all.
//!
//! Why the binary cares: a 16 MP solve allocates several times its peak memory over its run
//! (decoded frames, RGB planes, maps, encoder buffers), and on a virtual machine each fresh
//! 4 KiB page costs a fault and the kernel's zeroing: page faults were a sixth of a 16 MP
//! solve's CPU time (perf, `clear_page_erms`). Reusing freed memory and faulting large blocks
//! in 2 MiB pages removes most of that.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);
static INSTALLED: AtomicBool = AtomicBool::new(false);

/// Whether this build installs [`CountingAlloc`] in the `psscan` binary (feature
/// `count-alloc`); without it the counters stay at zero and peak memory is not measured.
pub const COUNTING: bool = cfg!(feature = "count-alloc");

/// Allocations at least this large are backed by transparent huge pages.
const HUGE_PAGE_MIN: usize = 4 << 20;

/// The system allocator, with every allocation of at least `HUGE_PAGE_MIN` bytes advised to
/// be backed by transparent huge pages (`madvise(MADV_HUGEPAGE)`; [`small_pages`] undoes it
/// for one buffer).
pub struct LargePageAlloc;

unsafe impl GlobalAlloc for LargePageAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        advise_if_large(System.alloc(layout), layout.size())
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        advise_if_large(System.alloc_zeroed(layout), layout.size())
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        advise_if_large(System.realloc(ptr, layout, new_size), new_size)
    }
}

fn advise_if_large(p: *mut u8, size: usize) -> *mut u8 {
    if !p.is_null() && size >= HUGE_PAGE_MIN {
        advise_huge_pages(p as usize, size);
    }
    p
}

/// Tells the C allocator (glibc) to keep freed memory for reuse rather than hand it back to
/// the kernel at once: blocks up to 32 MiB (its largest setting) come from the heap, and up to
/// 2 GiB of free memory stay mapped. Each reuse spares a page fault per page. Peak RSS grows a
/// little (2.75 -> 2.9 GB on a 16 MP solve). Call once, before the first allocation that
/// matters; a no-op off glibc.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes the allocator's thresholds; it is safe at any time.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
        libc::mallopt(libc::M_TOP_PAD, 256 << 20);
    }
}

/// The system allocator with [`LargePageAlloc`]'s huge pages, counting live bytes and their
/// peak.
pub struct CountingAlloc;

unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = LargePageAlloc.alloc(layout);
        if !p.is_null() {
            grow(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = LargePageAlloc.alloc_zeroed(layout);
        if !p.is_null() {
            grow(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        LargePageAlloc.dealloc(ptr, layout);
        CURRENT.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = LargePageAlloc.realloc(ptr, layout, new_size);
        if !p.is_null() {
            CURRENT.fetch_sub(layout.size(), Ordering::Relaxed);
            grow(new_size);
        }
        p
    }
}

#[inline]
fn grow(size: usize) {
    let now = CURRENT.fetch_add(size, Ordering::Relaxed) + size;
    PEAK.fetch_max(now, Ordering::Relaxed);
    if !INSTALLED.load(Ordering::Relaxed) {
        INSTALLED.store(true, Ordering::Relaxed);
    }
}

/// Whether the counting allocator is the global allocator of this process.
pub fn installed() -> bool {
    INSTALLED.load(Ordering::Relaxed)
}

/// Live heap bytes now.
pub fn current() -> usize {
    CURRENT.load(Ordering::Relaxed)
}

/// Starts a new peak measurement at the current live size.
pub fn reset_peak() {
    PEAK.store(CURRENT.load(Ordering::Relaxed), Ordering::Relaxed);
}

/// Highest live heap bytes since the last [`reset_peak`].
pub fn peak() -> usize {
    PEAK.load(Ordering::Relaxed)
}

/// Advises the kernel to back `data` with 4 KiB pages rather than the transparent huge pages
/// every large allocation is advised to use (Linux; a hint only, contents unchanged). For a
/// buffer written once in order and read once in order (a solve's outputs), where huge pages
/// save few TLB misses: each huge-page fault needs a free 2 MiB block, which on a fragmented
/// machine the kernel compacts memory to make (for advised memory, with `defrag` at its
/// default "madvise", while the fault waits), whereas a 4 KiB fault takes any free page, such
/// as those a solve gives back from its frames (`plane::FrameRelease`, whose buffers are
/// mostly in 4 KiB pages: calloc zeroes a reused heap block before it can be advised).
pub fn small_pages<T>(data: &mut [T]) {
    #[cfg(target_os = "linux")]
    advise_pages(
        data.as_mut_ptr() as usize,
        std::mem::size_of_val(data),
        libc::MADV_NOHUGEPAGE,
    );
    #[cfg(not(target_os = "linux"))]
    let _ = data;
}

/// Advises the kernel to back the `len` bytes at address `start` with transparent huge pages
/// (the whole 2 MiB pages inside them).
fn advise_huge_pages(start: usize, len: usize) {
    #[cfg(target_os = "linux")]
    advise_pages(start, len, libc::MADV_HUGEPAGE);
    #[cfg(not(target_os = "linux"))]
    let _ = (start, len);
}

/// `madvise(advice)` on the whole 2 MiB pages inside the `len` bytes at `start`.
#[cfg(target_os = "linux")]
fn advise_pages(start: usize, len: usize, advice: libc::c_int) {
    const HUGE: usize = 2 << 20;
    let (a, b) = (start.next_multiple_of(HUGE), (start + len) / HUGE * HUGE);
    if b > a {
        // SAFETY: the range lies inside one live allocation; the advice changes no contents,
        // only how the pages are backed.
        unsafe { libc::madvise(a as *mut libc::c_void, b - a, advice) };
    }
}
