//! `mbgate sim` and `mbgate demo`: the simulator's flags checked (exit 2 when bad),
//! tracing, the runtime, the signals (SIGHUP stops them too) and the console, then the
//! simulator (`crate::tools::sim`) or the demo (`crate::tools::demo`).

use super::exit;
use super::signals::{self, Stops};
use std::process::ExitCode;
use tokio_util::sync::CancellationToken;

use crate::cli::overrides::{choice, PortFlags};
use crate::config::{Framing, SerialConfig};
use crate::tools::sim::options::{self, BadFlags, DeviceArgs, Settings};
use crate::tools::sim::replay::args::ReplayArgs;
use crate::tools::sim::role::{self, Role};
use std::path::PathBuf;

/// `mbgate sim`: the device options and the serial port.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct SimArgs {
    /// The serial port or pty (e.g. one end of a socat pair).
    #[arg(
        long,
        value_name = "PATH",
        required_unless_present_any = ["listen", "summary", "pty"]
    )]
    serial: Option<PathBuf>,
    /// Make a pty instead, linked at PATH (as socat's `link=`), and serve on it: point
    /// the gateway's serial port at PATH. No relay process sits between the two ends,
    /// so a replayed device's reply time is not lengthened by one
    /// (docs/simulator.md "Replaying a device").
    #[arg(long, value_name = "PATH", conflicts_with_all = ["serial", "listen"])]
    pty: Option<PathBuf>,
    /// A device on the network instead: listen here (e.g. 127.0.0.1:1502) and serve
    /// one connection at a time, as a Modbus/TCP slave (--framing mbap) or a serial
    /// device server in raw TCP mode (--framing rtu or ascii).
    #[arg(long, value_name = "ADDR", conflicts_with = "serial")]
    pub(crate) listen: Option<std::net::SocketAddr>,
    /// With --listen: how many connections are served at once. 1 (the default): a
    /// second is closed at once, as a device server or a single-connection PLC does;
    /// more: a Modbus/TCP slave that several masters reach at once (--framing mbap).
    #[arg(
        long,
        value_name = "N",
        default_value_t = 1,
        requires = "listen",
        value_parser = clap::value_parser!(u16).range(1..=256)
    )]
    pub(crate) connections: u16,
    // Before the port's flags: their heading would carry over onto these.
    /// The device simulated.
    #[command(flatten)]
    pub(crate) device: DeviceArgs,
    /// A recorded device instead (src/tools/sim/replay/args.rs).
    #[command(flatten)]
    pub(crate) replay: ReplayArgs,
    /// The role it plays and where.
    #[command(flatten)]
    pub(crate) role: RoleArgs,
    /// The port's settings, as `mbgate run` takes them. On a pty, `--baud` paces the
    /// output as a UART would (the format's bits a byte: 10 for 8N1, 11 for 8E1), and
    /// without it the simulator answers at once; on a real port the UART does.
    #[command(flatten, next_help_heading = "serial port")]
    port: PortFlags,
    /// How frames are carried: mbap (the CIE-M10's serial Modbus/TCP), or rtu or ascii
    /// (generic profile and --replay only) [default: mbap; with --replay, as recorded].
    #[arg(long, value_parser = choice::<Framing>(), help_heading = "serial port")]
    pub(crate) framing: Option<Framing>,
}

impl SimArgs {
    /// The device and line settings, with this port's framing and, when given, its
    /// speed as the pace.
    pub(crate) fn settings(&self) -> Result<Settings, BadFlags> {
        options::framing_fits(&self.device, &self.replay, self.framing)?;
        let port = self.serial_config()?;
        let pace = self.port.given("baud").then_some(port.baud_rate);
        let mut s = options::settings(&self.device, &self.replay, self.framing, pace)?;
        // Paced as the port's format: an 8E1 character is 11 bits on a wire.
        s.char_bits = crate::line::port::kind::bits_per_char(&port);
        Ok(s)
    }

    /// The port settings: the defaults of `[serial]` and the flags given.
    pub(crate) fn serial_config(&self) -> Result<SerialConfig, BadFlags> {
        let mut cfg = SerialConfig {
            path: self
                .serial
                .as_deref()
                .map_or_else(String::new, |p| p.to_string_lossy().into_owned()),
            framing: self.framing.unwrap_or(Framing::Mbap),
            ..SerialConfig::default()
        };
        self.port
            .apply_serial(&mut cfg)
            .map_err(|e| e.to_string())?;
        Ok(cfg)
    }
}

/// Which side of the conversation the simulated device is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum RoleSide {
    /// It answers requests (the default).
    Slave,
    /// It sends the CIE-M10 master's queries every --poll-ms (cie-m10 profile).
    Master,
}

/// `mbgate sim`'s role flags: the CIE-M10 as the master of docs/protocol.md §3
/// (`--role master --poll-ms`); a slave (the default) answers requests.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct RoleArgs {
    /// slave answers requests; master sends, every --poll-ms, FC 03 for the slave's
    /// input port register and FC 16 with its own inputs to the slave's output port
    /// register (the --input-address and --output-address), and sets its outputs from
    /// what it read.
    #[arg(long, value_enum, default_value_t = RoleSide::Slave, help_heading = "role")]
    role: RoleSide,
    /// master: the communication period, in ms.
    #[arg(long, default_value_t = 1000, value_name = "MS", help_heading = "role")]
    poll_ms: u64,
    /// master: how long it waits for each reply, in ms [default: the period, at most 1000].
    #[arg(long, value_name = "MS", help_heading = "role")]
    timeout_ms: Option<u64>,
}

impl RoleArgs {
    /// The role as the simulator takes it.
    pub(crate) fn role(&self) -> Role {
        Role {
            side: match self.role {
                RoleSide::Slave => role::Side::Slave,
                RoleSide::Master => role::Side::Master,
            },
            poll_ms: self.poll_ms,
            timeout_ms: self.timeout_ms,
        }
    }
}

/// The simulator's log level: as asked, else `info` headless and `warn` under the
/// console, so packets do not scroll over the prompt.
fn sim_level(device: &crate::tools::sim::options::DeviceArgs) -> (String, bool) {
    let console = !device.headless && std::io::IsTerminal::is_terminal(&std::io::stdin());
    let level = device
        .log_level
        .clone()
        .unwrap_or_else(|| if console { "warn" } else { "info" }.into());
    (level, console)
}

/// `--pty LINK`: a pty made for the simulator, said in the log (its round trip is the
/// medium's delay).
async fn made_pty(
    link: &std::path::Path,
) -> Result<
    (tokio_serial::SerialStream, crate::tools::sim::pty::OwnPty),
    crate::tools::sim::pty::PtyError,
> {
    let (master, made) = crate::tools::sim::pty::OwnPty::make(link).await?;
    tracing::info!(
        "made a pty: {} is {} (round trip {} µs); point the gateway's serial port there",
        link.display(),
        made.slave(),
        made.round_trip().as_micros()
    );
    Ok((master, made))
}

/// `--replay FILE --summary`: what the files hold, and no more.
fn summary(
    settings: Result<crate::tools::sim::options::Settings, crate::tools::sim::options::BadFlags>,
) -> ExitCode {
    match settings {
        Ok(s) => {
            if let crate::tools::sim::Profile::Replay(r) = &s.device.profile {
                for w in &r.warnings {
                    eprintln!("mbgate: warning: {w}");
                }
                println!("{}", r.summary);
            }
            exit::code(exit::OK)
        }
        Err(e) => {
            eprintln!("mbgate: {e}");
            exit::code(exit::USAGE)
        }
    }
}

/// `mbgate sim`: bad options exit 2, a lost port is reopened, SIGTERM stops.
pub(crate) fn sim(args: SimArgs) -> ExitCode {
    use crate::tools::sim::serve::{self, SimPort};
    // Checked by `settings()` too, whose error is the one reported.
    let port = args.serial_config();
    let cie_m10 = args.device.profile == crate::tools::sim::options::ProfileName::CieM10
        && args.replay.replay.is_empty();
    let polling = args.role.role().polling(cie_m10, args.listen.is_some());
    let many = (args.connections > 1).then_some(args.connections);
    let settings = args
        .settings()
        .and_then(|s| polling.clone().map(|_| s))
        .and_then(|s| match many {
            Some(_) if s.framing() != crate::config::Framing::Mbap => {
                Err("--connections above 1 is a Modbus/TCP slave's: --framing mbap".into())
            }
            _ => Ok(s),
        });
    if args.replay.summary {
        return summary(settings);
    }
    let listen = args.listen;
    let pty = args.pty.clone();
    simulate(
        &args.device,
        settings,
        false,
        None,
        |mut settings, commands, shutdown| async move {
            if let (Some(addr), Some(n)) = (listen, many) {
                let listener = crate::tools::sim::tcp::bind(addr)
                    .await
                    .map_err(|source| Failed::Listen { addr, source })?;
                let n = usize::from(n);
                crate::tools::sim::tcp::run(settings.device, listener, n, commands, shutdown)
                    .await?;
                return Ok(());
            }
            // Held until the simulator stops: the pty and its link go with it.
            let mut own = None;
            let port = match (listen, pty) {
                (Some(addr), _) => SimPort::Listen(addr),
                (None, Some(link)) => {
                    let (master, made) = made_pty(&link).await?;
                    settings.medium = made.round_trip();
                    own = Some(made);
                    SimPort::Stream(master)
                }
                (None, None) => SimPort::Path(port?),
            };
            match polling? {
                Some(p) => {
                    crate::tools::sim::master::run(settings, p, port, commands, shutdown).await?;
                }
                None => serve::run(settings, port, commands, shutdown).await?,
            }
            drop(own);
            Ok(())
        },
    )
}

/// `mbgate demo`.
pub(crate) fn demo(args: crate::tools::demo::DemoArgs) -> ExitCode {
    if args.master.master {
        return master_demo(args);
    }
    let device = args.device.clone();
    let (_, console) = sim_level(&device);
    let (banner_shown, after_banner) = std::sync::mpsc::channel();
    simulate(
        &device,
        args.settings(),
        args.traffic,
        Some(after_banner),
        |settings, commands, shutdown| async move {
            let stats =
                crate::tools::demo::run(&args, settings, commands, shutdown, banner_shown).await?;
            // Under the console the log shows warnings only: the counters the log
            // gives at every stop are printed here instead.
            if console {
                println!("mbgate demo stopped: {stats}");
            }
            Ok(())
        },
    )
}

/// `mbgate demo --master`: the simulated master takes the device flags.
fn master_demo(args: crate::tools::demo::DemoArgs) -> ExitCode {
    let device = args.device.clone();
    let (banner_shown, after_banner) = std::sync::mpsc::channel();
    let settings = args.settings().and_then(|s| match s.device.profile {
        crate::tools::sim::Profile::CieM10(_) => Ok(s),
        crate::tools::sim::Profile::Generic(_) | crate::tools::sim::Profile::Replay(_) => {
            Err("--master is the cie-m10 profile's".into())
        }
    });
    simulate(
        &device,
        settings,
        args.traffic,
        Some(after_banner),
        |settings, commands, shutdown| async move {
            crate::tools::demo::master::run(&args, settings, commands, shutdown, banner_shown)
                .await?;
            Ok(())
        },
    )
}

/// What `sim` and `demo` share: the device options (exit 2 when bad), tracing, the
/// runtime, the signals and the console (shown once `console_after` says so, if given);
/// `body` runs the simulator.
fn simulate<F, Fut>(
    device: &crate::tools::sim::options::DeviceArgs,
    settings: Result<crate::tools::sim::options::Settings, crate::tools::sim::options::BadFlags>,
    traffic: bool,
    console_after: Option<std::sync::mpsc::Receiver<()>>,
    body: F,
) -> ExitCode
where
    F: FnOnce(
        crate::tools::sim::options::Settings,
        tokio::sync::mpsc::Receiver<crate::tools::sim::serve::ConsoleRequest>,
        CancellationToken,
    ) -> Fut,
    Fut: std::future::Future<Output = Result<(), Failed>>,
{
    let settings = match settings {
        Ok(s) => s,
        Err(e) => {
            eprintln!("mbgate: {e}");
            return exit::code(exit::USAGE);
        }
    };
    let (level, console) = sim_level(device);
    crate::ops::logging::init(&crate::config::LogConfig { level, traffic });
    let rt = match signals::runtime(exit::FAILED) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    finish(rt.block_on(async {
        let shutdown = signals::stop_on(Stops::TermIntHup);
        let commands = crate::tools::sim::terminal::start(console, shutdown.clone(), console_after);
        if console {
            // Ctrl-C leaves the cursor after `sim> `: end that line, so what
            // follows (and the shell's prompt) starts on its own.
            let ended = shutdown.clone();
            tokio::spawn(async move {
                ended.cancelled().await;
                println!();
            });
        }
        body(settings, commands, shutdown).await
    }))
}

/// Why a simulator or a demo stopped on an error (exit 1).
#[derive(Debug, thiserror::Error)]
enum Failed {
    #[error("cannot listen on {addr}")]
    Listen {
        addr: std::net::SocketAddr,
        source: std::io::Error,
    },
    #[error(transparent)]
    Io(#[from] std::io::Error),
    #[error(transparent)]
    Flags(#[from] BadFlags),
    #[error(transparent)]
    Sim(#[from] crate::tools::sim::serve::SimError),
    #[error(transparent)]
    Pty(#[from] crate::tools::sim::pty::PtyError),
    #[error(transparent)]
    Demo(#[from] crate::tools::demo::DemoError),
    #[error(transparent)]
    Master(#[from] crate::tools::demo::master::MasterDemoError),
}

/// The end of a simulator's run: 0, or the error (and its sources) and 1.
fn finish(result: Result<(), Failed>) -> ExitCode {
    match result {
        Ok(()) => exit::code(exit::OK),
        Err(e) => exit::failed(exit::said(&e)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Parity;
    use clap::Parser;

    /// The port takes `mbgate run`'s flags, ranges and defaults; `--baud` also paces.
    #[test]
    fn the_port_takes_run_s_flags() {
        #[derive(Parser)]
        struct S {
            #[command(flatten)]
            s: SimArgs,
        }
        let sim = |args: &[&str]| {
            let line = ["t", "--serial", "/dev/ttyS9", "--profile", "generic"];
            S::try_parse_from(line.iter().chain(args)).unwrap().s
        };
        let s = sim(&["--baud", "9600", "--parity", "even", "--framing", "rtu"]);
        let port = s.serial_config().unwrap();
        assert_eq!((port.path.as_str(), port.baud_rate), ("/dev/ttyS9", 9600));
        assert_eq!((port.parity, port.framing), (Parity::Even, Framing::Rtu));
        assert_eq!(s.settings().unwrap().baud, Some(9600));
        // Paced as the format is: 8E1 is 11 bits a character, 8N1 10.
        assert_eq!(s.settings().unwrap().char_bits, 11);
        let s = sim(&[]);
        assert_eq!(s.settings().unwrap().char_bits, 10);
        assert_eq!(
            s.serial_config().unwrap(),
            SerialConfig {
                path: "/dev/ttyS9".into(),
                ..SerialConfig::default()
            }
        );
        assert_eq!(
            s.settings().unwrap().baud,
            None,
            "no --baud given: on a pty nothing paces it (serve.rs)"
        );
        let bad = sim(&["--data-bits", "9"]).settings().unwrap_err();
        assert_eq!(bad.to_string(), "--data-bits: must be 7 or 8, got 9");
    }
}
