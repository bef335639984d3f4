//! The `psscan` binary: parses arguments and hands over to the library (see `cli`).

mod cli;

// The system allocator with large blocks in huge pages (see `psscan::alloc`); with feature
// `count-alloc` it also counts heap bytes, so `psscan bench` can report the solve's peak memory.
#[cfg(not(feature = "count-alloc"))]
#[global_allocator]
static ALLOC: psscan::alloc::LargePageAlloc = psscan::alloc::LargePageAlloc;
#[cfg(feature = "count-alloc")]
#[global_allocator]
static ALLOC: psscan::alloc::CountingAlloc = psscan::alloc::CountingAlloc;

fn main() {
    psscan::alloc::keep_freed_memory();
    std::process::exit(cli::run());
}
