//! `mbgate wire` (docs/simulator.md, "A virtual line"): exit 0 when stopped by SIGTERM
//! or SIGINT, 1 when it failed, 2 bad arguments.

use super::exit;
use super::signals::{self, Stops};
use crate::wire::{run, WireError};
use std::process::ExitCode;

pub(crate) use crate::wire::WireArgs;

/// `mbgate wire`.
pub(crate) fn main(args: WireArgs) -> ExitCode {
    let rt = match signals::runtime(exit::FAILED) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    match rt.block_on(async { run(&args, signals::stop_on(Stops::TermInt)).await }) {
        Ok(()) => exit::code(exit::OK),
        Err(WireError::Option(e)) => exit::usage(e),
        Err(e) => exit::failed(e),
    }
}
