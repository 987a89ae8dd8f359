//! `mbgate status`: exit 0 healthy, 1 not (a line's port not open, or a unit not
//! answering), 3 the gateway could not be asked, 2 bad arguments.

use super::exit;
use crate::ops::metrics::status_command::{ask, turn_on};
use std::process::ExitCode;

/// `mbgate status`'s flags.
#[derive(Debug, clap::Args)]
pub(crate) struct StatusArgs {
    /// The gateway's metrics listener (its `metrics.listen`)
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:9502")]
    metrics: String,
}

/// `mbgate status`.
pub(crate) fn main(args: StatusArgs) -> ExitCode {
    match ask(&args.metrics) {
        Ok((report, healthy)) => {
            print!("{report}");
            exit::ok_if(healthy)
        }
        Err(e) => {
            eprintln!("mbgate: cannot ask the gateway at {}: {e}", args.metrics);
            eprint!("{}", turn_on(&args.metrics));
            exit::code(exit::OTHER)
        }
    }
}
