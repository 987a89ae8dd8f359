//! `mbgate scan` (docs/scan.md): exit 0 something answered, 1 nothing did or the port
//! could not be used (held by a gateway: the process is named), 2 bad arguments.
//! Ctrl-C ends it with what was found so far.

use super::exit;
use super::signals::{self, Stops};
use crate::scan::{scan, ScanError};
use std::process::ExitCode;

pub(crate) use crate::scan::ScanArgs;

/// `mbgate scan`.
pub(crate) fn main(args: ScanArgs) -> ExitCode {
    let rt = match signals::runtime(exit::FAILED) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    let scanned = rt.block_on(async { scan(&args, signals::stop_on(Stops::Interrupt)).await });
    match scanned {
        Ok(s) => {
            let (text, found) = s.said(&args);
            print!("{text}");
            exit::ok_if(found)
        }
        Err(ScanError::Option(e)) => exit::usage(e),
        Err(e) => exit::failed(e),
    }
}
