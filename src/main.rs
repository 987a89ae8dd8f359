//! The command line (design.md §3). Parses, loads the configuration, starts tracing and
//! runs; everything else lives in the library.

use anyhow::Context as _;
use clap::{Parser, Subcommand};
use mbgate::config::{self, Config, Overrides};
use std::path::PathBuf;
use std::process::ExitCode;
use tokio_util::sync::CancellationToken;

/// Modbus/TCP to serial gateway for the Sollae ezTCP CIE-M10/H10 "serial Modbus/TCP"
/// mode: many TCP masters, one serial device.
#[derive(Debug, Parser)]
#[command(name = "mbgate", version, about)]
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
    /// Validate a configuration file and print the effective configuration.
    CheckConfig {
        /// The file to check.
        file: PathBuf,
        #[command(flatten)]
        overrides: Overrides,
    },
}

/// Exit code for a bad configuration or bad arguments (design.md §3; clap uses 2 too).
const EXIT_CONFIG: u8 = 2;

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::CheckConfig { file, overrides } => match effective(Some(file), &overrides) {
            Ok(cfg) => {
                print!("{}", config::to_toml(&cfg));
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
            let cfg = match effective(config, &overrides) {
                Ok(cfg) => cfg,
                Err(e) => {
                    eprintln!("{prefix}mbgate: {e}");
                    return ExitCode::from(EXIT_CONFIG);
                }
            };
            match run(cfg) {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    eprintln!("{prefix}mbgate: {e:#}");
                    ExitCode::FAILURE
                }
            }
        }
    }
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

fn run(cfg: Config) -> anyhow::Result<()> {
    mbgate::logging::init(&cfg.log);
    // One thread: the serial line is the bottleneck, and a single-threaded runtime has
    // the smallest footprint and no cross-thread wake-ups on the reply path.
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the runtime")?;
    rt.block_on(async {
        let shutdown = CancellationToken::new();
        tokio::spawn(watch_signals(shutdown.clone()));
        mbgate::gateway::run(cfg, shutdown).await?;
        Ok(())
    })
}

/// SIGTERM (systemd stop) or SIGINT (Ctrl-C) starts a graceful shutdown.
async fn watch_signals(shutdown: CancellationToken) {
    use tokio::signal::unix::{signal, SignalKind};
    let (Ok(mut term), Ok(mut int)) = (
        signal(SignalKind::terminate()),
        signal(SignalKind::interrupt()),
    ) else {
        tracing::error!("cannot install signal handlers");
        return;
    };
    tokio::select! {
        _ = term.recv() => tracing::info!("SIGTERM received"),
        _ = int.recv() => tracing::info!("SIGINT received"),
    }
    shutdown.cancel();
}
