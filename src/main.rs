//! The command line (docs/design.md §3). Parses, loads the configuration, starts tracing and
//! runs; everything else lives in the library.

#![deny(unsafe_code)]

use anyhow::Context as _;
use clap::{Parser, Subcommand};
use mbgate::cli_overrides::Overrides;
use mbgate::config::{self, Config};
use std::path::PathBuf;
use std::process::ExitCode;
use tokio_util::sync::CancellationToken;

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
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
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
    Read(mbgate::client::ReadArgs),
    /// Write coils or registers (FC 05, 06, 0F, 10; 17 with --read), print the reply.
    ///
    /// To a gateway (--tcp) or a device on a serial port (--serial). Exit code 0 on a
    /// reply, 3 on an exception, 1 on no answer, 2 on bad arguments.
    Write(mbgate::client::WriteArgs),
    /// A simulated device on a serial port or pty (a CIE-M10, or generic devices).
    ///
    /// With a console when stdin is a terminal (`help` lists its commands); headless
    /// otherwise, logging each packet.
    Sim(mbgate::sim::options::SimArgs),
    /// Find what is on a bus: baud rate, format, framing and unit ids, by reads only.
    ///
    /// Tries each setting (19200 8E1 and 9600 8N1 RTU first) with FC 03 of one
    /// register to each unit; a setting is proven by any frame with a good CRC or LRC,
    /// and left after --give-up units without one. Then each unit found is asked its
    /// identity (FC 43/14, FC 17). Ends with a table and a [[line]] block for
    /// mbgate.toml (docs/scan.md). Exit code 0 something answered, 1 nothing did or
    /// the port could not be used (held by a gateway: the process is named), 2 bad
    /// arguments.
    Scan(mbgate::scan::ScanArgs),
    /// A virtual serial line: two ptys joined like a null-modem cable, at the wire's pace.
    ///
    /// Each byte takes its time at its sender's baud rate (start, data, parity and stop
    /// bits) and arrives as the receiver's UART takes it: garbled where the two ends'
    /// baud rates or formats differ. Optional loss, noise and RS-232 echo, seeded. Runs
    /// until Ctrl-C or SIGTERM (docs/simulator.md, "A virtual line").
    Wire(mbgate::wire::WireArgs),
    /// No hardware: a pty pair, a simulated CIE-M10 and the gateway, in one process.
    Demo(mbgate::demo::DemoArgs),
    /// Ask a running gateway how its lines are: a summary per line and unit.
    ///
    /// From its metrics listener (`[metrics] listen`, off unless given an address).
    /// Exit code 0 healthy, 1 not (a line's port not open, or a unit not answering:
    /// three timeouts in a row, no reply since, the last timeout within a minute), 3
    /// the gateway could not be asked, 2 bad arguments.
    Status(mbgate::metrics::status_command::StatusArgs),
    /// Capture a running gateway's frames to pcapng, for Wireshark (docs/capture.md).
    ///
    /// Every frame each master sent and received, every frame on each line, and the
    /// bytes the gateway dropped with why; over its control socket (root, or the
    /// service's user or group). Exit code 0 when the capture ended as asked (--count,
    /// --seconds, Ctrl-C), 1 when it could not run or its output failed, 2 bad
    /// arguments.
    Capture(mbgate::control::capture::CaptureArgs),
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
    Reload(mbgate::control::reload::ReloadArgs),
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

/// Exit code for a bad configuration or bad arguments (docs/design.md §3; clap uses 2 too).
const EXIT_CONFIG: u8 = 2;

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Read(args) => mbgate::client::read_main(args),
        Command::Write(args) => mbgate::client::write_main(args),
        Command::Sim(args) => sim(args),
        Command::Demo(args) => demo(args),
        Command::Wire(args) => mbgate::wire::main(args),
        Command::Scan(args) => mbgate::scan::main(args),
        Command::Status(args) => mbgate::metrics::status_command::main(args),
        Command::Generate(what) => generate(what),
        Command::Reload(args) => mbgate::control::reload::main(args),
        Command::Capture(args) => mbgate::control::capture::main(args),
        Command::CheckConfig {
            file,
            print,
            lines,
            overrides,
        } => match checked(Some(file.clone()), &overrides) {
            Ok(cfg) => {
                if lines {
                    print!("{}", config::to_toml_lines(&cfg));
                } else if print {
                    print!("{}", config::to_toml(&cfg));
                } else {
                    println!("OK: {}", file.display());
                    print!("{}", config::describe::summary(&cfg));
                }
                for warning in mbgate::gateway::warnings(&cfg) {
                    eprintln!("mbgate: warning: {warning}");
                }
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("mbgate: {e}");
                ExitCode::from(EXIT_CONFIG)
            }
        },
        Command::Run { config, overrides } => {
            // Under journald these lines get the error priority too.
            let prefix = mbgate::logging::error_prefix();
            let cfg = match checked(config.clone(), &overrides) {
                Ok(cfg) => cfg,
                Err(e) => {
                    eprintln!("{prefix}mbgate: {e}");
                    return ExitCode::from(EXIT_CONFIG);
                }
            };
            // A reload reads the file again and puts the same flags on top.
            let load = Box::new(move || effective(config.clone(), &overrides));
            match run(cfg, load) {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    eprintln!("{prefix}mbgate: {e:#}");
                    ExitCode::FAILURE
                }
            }
        }
    }
}

/// `mbgate generate`: the man pages into a directory, or a completion script on
/// stdout.
fn generate(what: Generate) -> ExitCode {
    use clap::CommandFactory;
    let written = match what {
        Generate::Man { dir } => mbgate::manual::man_pages(Cli::command(), &dir).map(|files| {
            for f in files {
                println!("{}", f.display());
            }
        }),
        Generate::Completions { shell } => {
            mbgate::manual::completion(Cli::command(), shell, &mut std::io::stdout())
        }
    };
    finish(written.map_err(anyhow::Error::from))
}

/// The file (or the defaults), then the flags on top.
fn effective(file: Option<PathBuf>, overrides: &Overrides) -> Result<Config, config::ConfigError> {
    let mut cfg = match file {
        Some(path) => config::load(&path)?,
        None => Config::default(),
    };
    overrides.apply(&mut cfg)?;
    Ok(cfg)
}

/// [`effective`], and every TLS file it names loaded: a certificate or key that cannot
/// be used is a bad configuration too (docs/security.md).
fn checked(file: Option<PathBuf>, overrides: &Overrides) -> Result<Config, String> {
    let cfg = effective(file, overrides).map_err(|e| e.to_string())?;
    mbgate::tls::check(&cfg).map_err(|e| e.to_string())?;
    Ok(cfg)
}

fn run(cfg: Config, load: mbgate::reload::Loader) -> anyhow::Result<()> {
    mbgate::logging::init(&cfg.log);
    let rt = runtime()?;
    rt.block_on(async {
        let shutdown = CancellationToken::new();
        tokio::spawn(watch_signals(shutdown.clone(), Hangup::Reloads));
        // Every line, whichever side its device is on (a gateway of master lines
        // alone listens for no Modbus/TCP master).
        mbgate::gateway::run_reloading(cfg, load, shutdown).await?;
        Ok(())
    })
}

/// The simulator's log level: as asked, else `info` headless and `warn` under the
/// console, so packets do not scroll over the prompt.
fn sim_level(device: &mbgate::sim::options::DeviceArgs) -> (String, bool) {
    let console = !device.headless && std::io::IsTerminal::is_terminal(&std::io::stdin());
    let level = device
        .log_level
        .clone()
        .unwrap_or_else(|| if console { "warn" } else { "info" }.into());
    (level, console)
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    mbgate::runtime::new().context("starting the runtime")
}

/// `mbgate sim`: bad options exit 2, a lost port is reopened, SIGTERM stops.
fn sim(args: mbgate::sim::options::SimArgs) -> ExitCode {
    use mbgate::sim::serve::{self, Port};
    // Checked by `settings()` too, whose error is the one reported.
    let port = args.serial_config();
    let cie_m10 = args.device.profile == mbgate::sim::options::ProfileName::CieM10
        && args.replay.replay.is_empty();
    let polling = args.role.polling(cie_m10, args.listen.is_some());
    let many = (args.connections > 1).then_some(args.connections);
    let settings = args
        .settings()
        .and_then(|s| polling.clone().map(|_| s))
        .and_then(|s| match many {
            Some(_) if s.framing() != mbgate::config::Framing::Mbap => {
                Err("--connections above 1 is a Modbus/TCP slave's: --framing mbap".into())
            }
            _ => Ok(s),
        });
    if args.replay.summary {
        // `--replay FILE --summary`: what the files hold, and no more.
        return match settings {
            Ok(s) => {
                if let mbgate::sim::Profile::Replay(r) = &s.device.profile {
                    for w in &r.warnings {
                        eprintln!("mbgate: warning: {w}");
                    }
                    println!("{}", r.summary);
                }
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("mbgate: {e}");
                ExitCode::from(EXIT_CONFIG)
            }
        };
    }
    let listen = args.listen;
    simulate(
        &args.device,
        settings,
        false,
        None,
        |settings, commands, shutdown| async move {
            if let (Some(addr), Some(n)) = (listen, many) {
                let listener = mbgate::sim::tcp::bind(addr)
                    .await
                    .with_context(|| format!("cannot listen on {addr}"))?;
                let n = usize::from(n);
                mbgate::sim::tcp::run(settings.device, listener, n, commands, shutdown).await?;
                return Ok(());
            }
            let port = match listen {
                Some(addr) => Port::Listen(addr),
                None => Port::Path(port.map_err(anyhow::Error::msg)?),
            };
            match polling.map_err(anyhow::Error::msg)? {
                Some(p) => {
                    mbgate::sim::master::run(settings, p, port, commands, shutdown).await?;
                }
                None => serve::run(settings, port, commands, shutdown).await?,
            }
            Ok(())
        },
    )
}

/// `mbgate demo`.
fn demo(args: mbgate::demo::DemoArgs) -> ExitCode {
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
                mbgate::demo::run(&args, settings, commands, shutdown, banner_shown).await?;
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
fn master_demo(args: mbgate::demo::DemoArgs) -> ExitCode {
    let device = args.device.clone();
    let (banner_shown, after_banner) = std::sync::mpsc::channel();
    let settings = args.settings().and_then(|s| match s.device.profile {
        mbgate::sim::Profile::CieM10(_) => Ok(s),
        mbgate::sim::Profile::Generic(_) | mbgate::sim::Profile::Replay(_) => {
            Err("--master is the cie-m10 profile's".into())
        }
    });
    simulate(
        &device,
        settings,
        args.traffic,
        Some(after_banner),
        |settings, commands, shutdown| async move {
            mbgate::demo::master::run(&args, settings, commands, shutdown, banner_shown).await?;
            Ok(())
        },
    )
}

/// What `sim` and `demo` share: the device options (exit 2 when bad), tracing, the
/// runtime, the signals and the console (shown once `console_after` says so, if given);
/// `body` runs the simulator.
fn simulate<F, Fut>(
    device: &mbgate::sim::options::DeviceArgs,
    settings: Result<mbgate::sim::options::Settings, mbgate::sim::options::BadFlags>,
    traffic: bool,
    console_after: Option<std::sync::mpsc::Receiver<()>>,
    body: F,
) -> ExitCode
where
    F: FnOnce(
        mbgate::sim::options::Settings,
        tokio::sync::mpsc::Receiver<mbgate::sim::serve::ConsoleRequest>,
        CancellationToken,
    ) -> Fut,
    Fut: std::future::Future<Output = anyhow::Result<()>>,
{
    let settings = match settings {
        Ok(s) => s,
        Err(e) => {
            eprintln!("mbgate: {e}");
            return ExitCode::from(EXIT_CONFIG);
        }
    };
    let (level, console) = sim_level(device);
    mbgate::logging::init(&mbgate::config::LogConfig { level, traffic });
    finish(runtime().and_then(|rt| {
        rt.block_on(async {
            let shutdown = CancellationToken::new();
            tokio::spawn(watch_signals(shutdown.clone(), Hangup::Stops));
            let commands = mbgate::sim::terminal::start(console, shutdown.clone(), console_after);
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
        })
    }))
}

fn finish(result: anyhow::Result<()>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("mbgate: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// What SIGHUP does.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Hangup {
    /// `mbgate run`: a reload (`systemctl reload`), handled by the gateway
    /// (`mbgate::reload`).
    Reloads,
    /// `sim`, `demo`: a closed terminal stops them, gracefully (SIGHUP's default
    /// action would end the process at once).
    Stops,
}

/// SIGTERM (systemd stop), SIGINT (Ctrl-C) and, for `sim` and `demo`, SIGHUP start a
/// graceful shutdown. The handlers are installed before this returns, so a signal
/// that comes at once is not fatal; the future it returns waits for one.
fn watch_signals(
    shutdown: CancellationToken,
    hangup: Hangup,
) -> impl std::future::Future<Output = ()> {
    use tokio::signal::unix::{signal, SignalKind};
    let handlers = (
        signal(SignalKind::terminate()),
        signal(SignalKind::interrupt()),
        (hangup == Hangup::Stops).then(|| signal(SignalKind::hangup())),
    );
    async move {
        let (Ok(mut term), Ok(mut int)) = (handlers.0, handlers.1) else {
            tracing::error!("cannot install signal handlers");
            return;
        };
        let mut hup = handlers.2.and_then(Result::ok);
        let hung_up = async {
            match &mut hup {
                Some(hup) => hup.recv().await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = term.recv() => tracing::info!("SIGTERM received"),
            _ = int.recv() => tracing::info!("SIGINT received"),
            _ = hung_up => tracing::info!("SIGHUP received; stopping"),
        }
        shutdown.cancel();
    }
}
