//! The `psscan` binary: parses arguments and hands over to the library (see `cli`).

mod cli;

fn main() {
    std::process::exit(cli::run());
}
