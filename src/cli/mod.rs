//! The command line, once for every subcommand (docs/design.md §3): the argument
//! types (`Cli` and each subcommand's flags, which the man pages and completions are
//! generated from, `crate::cli::manual`), the runtime and signals (`signals.rs`) and the
//! exit codes (`exit.rs`). Each subcommand's file turns its flags into the plain
//! options of the room that does the work, runs it, and turns its typed outcome or
//! error into a message and an exit code. `src/main.rs` only calls [`main`].

mod capture;
mod client;
mod client_args;
pub(crate) mod exit;
mod gateway;
pub(crate) mod manual;
pub mod overrides;
mod password;
mod reload;
pub mod runtime;
mod scan;
mod signals;
pub(crate) mod sim;
mod status;
mod wire;

use crate::cli::overrides::Overrides;
use clap::{CommandFactory as _, Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

/// Modbus/TCP to serial gateway for MBAP (Sollae ezTCP CIE-M10/H10 serial Modbus/TCP
/// mode), Modbus RTU and Modbus ASCII devices: many TCP masters, one serial line.
#[derive(Debug, Parser)]
#[command(
    name = "mbgate",
    version,
    about,
    long_about = "mbgate lets Modbus/TCP masters (SCADA, HMIs, PLCs, scripts) reach \
devices that only have a serial port: Modbus RTU or ASCII devices on an RS-232 line or \
an RS-485 bus, or a device that takes whole MBAP frames such as a Sollae ezTCP \
CIE-M10/H10 in serial Modbus/TCP mode. It multiplexes many masters onto one line, \
several lines behind one address, devices on the network too.\n\n\
Try it without hardware: mbgate demo. Check a configuration: mbgate check-config FILE \
(see mbgate.toml(5)). Run it: mbgate run --config FILE, or as the systemd service \
mbgate@NAME, which reads /etc/mbgate/NAME.toml. Ask a running gateway: mbgate status."
)]
pub(crate) struct Cli {
    #[command(subcommand)]
    command: CliCommand,
}

#[derive(Debug, Subcommand)]
enum CliCommand {
    /// Run the gateway in the foreground (systemd does this).
    Run {
        /// Configuration file (TOML, see config/mbgate.toml); without it, the defaults.
        #[arg(long, short = 'c', value_name = "FILE")]
        config: Option<PathBuf>,
        #[command(flatten)]
        overrides: Overrides,
    },
    /// Validate a configuration file and say what it sets up.
    ///
    /// Prints "OK" and the effective setup in a few lines (with --print, the whole
    /// effective configuration), and on stderr the warnings `run` would give. Exit code
    /// 0 valid, 2 not (the message names the file, line and key).
    CheckConfig {
        /// The file to check.
        file: PathBuf,
        /// Print the whole effective configuration, every key with its value, as TOML
        #[arg(long)]
        print: bool,
        /// Print the whole effective configuration as [[line]] and [[listen]] tables
        /// (docs/design.md §4.1)
        #[arg(long)]
        lines: bool,
        #[command(flatten)]
        overrides: Overrides,
    },
    /// Read coils, discrete inputs or registers (FC 01..04) and print them.
    ///
    /// From a gateway (--tcp) or a device on a serial port (--serial): does the device
    /// answer? Exit code 0 on a reply, 3 on an exception, 1 on no answer, 2 on bad
    /// arguments.
    Read(client::ReadArgs),
    /// Write coils or registers (FC 05, 06, 0F, 10; 17 with --read), print the reply.
    ///
    /// To a gateway (--tcp) or a device on a serial port (--serial). Exit code 0 on a
    /// reply, 3 on an exception, 1 on no answer, 2 on bad arguments.
    Write(client::WriteArgs),
    /// A simulated device on a serial port or pty (a CIE-M10, or generic devices).
    ///
    /// With a console when stdin is a terminal (`help` lists its commands); headless
    /// otherwise, logging each packet.
    Sim(sim::SimArgs),
    /// Find what is on a bus: baud rate, format, framing and unit ids, by reads only.
    ///
    /// Tries each setting (19200 8E1 and 9600 8N1 RTU first) with FC 03 of one
    /// register to each unit; a setting is proven by any frame with a good CRC or LRC,
    /// and left after --give-up units without one. Then each unit found is asked its
    /// identity (FC 43/14, FC 17). Ends with a table and a [[line]] block for
    /// mbgate.toml (docs/scan.md). Exit code 0 something answered, 1 nothing did or
    /// the port could not be used (held by a gateway: the process is named), 2 bad
    /// arguments.
    Scan(scan::ScanArgs),
    /// A virtual serial line: two ptys joined like a null-modem cable, at the wire's pace.
    ///
    /// Each byte takes its time at its sender's baud rate (start, data, parity and stop
    /// bits) and arrives as the receiver's UART takes it: garbled where the two ends'
    /// baud rates or formats differ. Optional loss, noise and RS-232 echo, seeded. Runs
    /// until Ctrl-C or SIGTERM (docs/simulator.md, "A virtual line").
    Wire(wire::WireArgs),
    /// No hardware: a pty pair, a simulated CIE-M10 and the gateway, in one process.
    Demo(crate::tools::demo::DemoArgs),
    /// Ask a running gateway how its lines are: a summary per line and unit.
    ///
    /// Over its control socket when there is one (root, or the service's user or
    /// group: no password), else from its metrics listener (`[metrics] listen`, off
    /// unless given an address; https and a user where its web configuration asks).
    /// Exit code 0 healthy, 1 not (a line's port not open, or a unit not answering:
    /// three timeouts in a row, no reply since, the last timeout within a minute), 3
    /// the gateway could not be asked, 2 bad arguments.
    Status(status::StatusArgs),
    /// Make a bcrypt hash of a password, for the metrics listener's users.
    ///
    /// Reads the password from the terminal (twice, not shown) or the first line of
    /// standard input, never from the command line; prints the hash, or with --user a
    /// line for `basic_auth_users` in the web configuration file (docs/watching.md).
    /// Exit code 0 printed, 1 the two passwords differ or none was read, 2 bad
    /// arguments.
    HashPassword(password::HashArgs),
    /// Capture a running gateway's frames to pcapng, for Wireshark (docs/capture.md).
    ///
    /// Every frame each master sent and received, every frame on each line, and the
    /// bytes the gateway dropped with why; over its control socket (root, or the
    /// service's user or group). Exit code 0 when the capture ended as asked (--count,
    /// --seconds, Ctrl-C), 1 when it could not run or its output failed, 2 bad
    /// arguments.
    Capture(capture::CaptureArgs),
    /// Man pages and shell completions, generated from this command line.
    ///
    /// The .deb installs them; for an install with cargo: `mbgate generate man DIR`,
    /// then `man -l DIR/mbgate.1`, and `mbgate generate completions bash >
    /// ~/.local/share/bash-completion/completions/mbgate`.
    #[command(subcommand)]
    Generate(Generate),
    /// Have a running gateway read its configuration file again, and say what changed.
    ///
    /// As SIGHUP (`systemctl reload`), asked over its control socket (root, or the
    /// service's user or group: the one `mbgate capture` uses). Prints each change
    /// applied, line by line and key by key, what waits for a restart, and each TLS
    /// listener's certificate read again. Exit code 0 taken, 1 refused (the file does
    /// not load, or adds or removes a line; the running configuration stays), 3 the
    /// gateway could not be asked, 2 bad arguments.
    Reload(reload::ReloadArgs),
}

/// What `mbgate generate` writes.
#[derive(Debug, Subcommand)]
enum Generate {
    /// Write the man pages into DIR: mbgate(1), mbgate-SUBCOMMAND(1) for each
    /// subcommand, and mbgate.toml(5), the configuration file.
    Man {
        /// Where to write them (it must exist).
        #[arg(value_name = "DIR")]
        dir: PathBuf,
    },
    /// Print the completion script for SHELL.
    Completions {
        /// bash, zsh, fish, elvish or powershell.
        #[arg(value_name = "SHELL")]
        shell: clap_complete::Shell,
    },
}

/// `mbgate`: parse the command line, run the subcommand, give its exit code.
pub fn main() -> ExitCode {
    match Cli::parse().command {
        CliCommand::Read(args) => client::read(args),
        CliCommand::Write(args) => client::write(args),
        CliCommand::Sim(args) => sim::sim(args),
        CliCommand::Demo(args) => sim::demo(args),
        CliCommand::Wire(args) => wire::main(args),
        CliCommand::Scan(args) => scan::main(args),
        CliCommand::Status(args) => status::main(args),
        CliCommand::HashPassword(args) => password::main(args),
        CliCommand::Generate(what) => generate(what),
        CliCommand::Reload(args) => reload::main(args),
        CliCommand::Capture(args) => capture::main(args),
        CliCommand::CheckConfig {
            file,
            print,
            lines,
            overrides,
        } => gateway::check_config(file, print, lines, &overrides),
        CliCommand::Run { config, overrides } => gateway::run(config, overrides),
    }
}

/// The command line as clap sees it: what the man pages and completions are made of.
pub(crate) fn command() -> clap::Command {
    Cli::command()
}

/// `mbgate generate`: the man pages into a directory, or a completion script on
/// stdout.
fn generate(what: Generate) -> ExitCode {
    let written = match what {
        Generate::Man { dir } => crate::cli::manual::man_pages(command(), &dir).map(|files| {
            for f in files {
                println!("{}", f.display());
            }
        }),
        Generate::Completions { shell } => {
            crate::cli::manual::completion(command(), shell, &mut std::io::stdout())
        }
    };
    match written {
        Ok(()) => exit::code(exit::OK),
        Err(e) => exit::failed(e),
    }
}

#[cfg(test)]
mod tests;
