//! `mbgate wire` (docs/simulator.md, "A virtual line"): exit 0 when stopped by SIGTERM
//! or SIGINT, 1 when it failed, 2 bad arguments.

use super::exit;
use super::signals::{self, Stops};
use crate::tools::wire::{run, EndSpec, WireError, WireOptions};
use std::path::PathBuf;
use std::process::ExitCode;

/// `mbgate wire`'s flags.
#[derive(Debug, clap::Args)]
pub(crate) struct WireArgs {
    /// End A: the path to make (a symbolic link to its pty, removed at exit).
    #[arg(value_name = "A")]
    a_path: PathBuf,
    /// End B: likewise.
    #[arg(value_name = "B")]
    b_path: PathBuf,
    /// Both ends' format, FORMAT or BAUD,FORMAT: 8N1, 8E1, 8O1, 8N2, 7E1...; or
    /// `auto`: the parity and stop bits the program set, where a pty still shows them
    /// (PARODD: odd; INPCK without it: even, as serialport and so mbgate set it;
    /// pyserial's even parity reads as none). A baud rate given here is used whatever
    /// the program sets; otherwise each end's speed is the one its program set.
    #[arg(long, value_name = "[BAUD,]FORMAT", default_value = "8N1")]
    format: EndSpec,
    /// End A's format, as --format (which it overrides).
    #[arg(long = "a", value_name = "[BAUD,]FORMAT")]
    a_spec: Option<EndSpec>,
    /// End B's format, as --format (which it overrides).
    #[arg(long = "b", value_name = "[BAUD,]FORMAT")]
    b_spec: Option<EndSpec>,
    /// The share of characters lost on the wire, 0 to 1 (the receiver hears an idle
    /// line for them).
    #[arg(long, default_value_t = 0.0, value_name = "P")]
    loss: f64,
    /// The share of characters with one bit flipped on the wire, 0 to 1 (any bit:
    /// a data bit, the parity bit, the start or a stop bit).
    #[arg(long, default_value_t = 0.0, value_name = "P")]
    noise: f64,
    /// RS-232 echo: each end hears what it sends too (as it left, before loss and
    /// noise), as a 2-wire RS-485 transceiver or a loopback adapter does.
    #[arg(long)]
    echo: bool,
    /// The seed of loss and noise: the same seed, the same faults for the same bytes.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

impl WireArgs {
    /// The options the line runs with: each end's spec, else `--format`.
    fn options(self) -> WireOptions {
        WireOptions {
            specs: [
                self.a_spec.unwrap_or(self.format),
                self.b_spec.unwrap_or(self.format),
            ],
            paths: [self.a_path, self.b_path],
            loss: self.loss,
            noise: self.noise,
            echo: self.echo,
            seed: self.seed,
        }
    }
}

/// `mbgate wire`.
pub(crate) fn main(args: WireArgs) -> ExitCode {
    let rt = match signals::runtime(exit::FAILED) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    let options = args.options();
    match rt.block_on(async { run(&options, signals::stop_on(Stops::TermInt)).await }) {
        Ok(()) => exit::code(exit::OK),
        Err(WireError::Option(e)) => exit::usage(e),
        Err(e) => exit::failed(e),
    }
}
