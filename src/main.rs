//! The `psscan` binary: parses arguments and hands over to the library (see `cli`).

mod cli;

// Counts heap bytes so `psscan bench` can report the solve's peak memory (feature
// `count-alloc`; other builds keep the system allocator).
#[cfg(feature = "count-alloc")]
#[global_allocator]
static ALLOC: psscan::alloc::CountingAlloc = psscan::alloc::CountingAlloc;

fn main() {
    std::process::exit(cli::run());
}
