//! The command line (docs/design.md §3): everything, from the argument types to the
//! exit codes, is the library's `cli` room; this only calls it.

#![deny(unsafe_code)]

fn main() -> std::process::ExitCode {
    mbgate::cli::main()
}
