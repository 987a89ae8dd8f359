//! `mbgate sim` and `mbgate demo`: the simulator's flags checked (exit 2 when bad),
//! tracing, the runtime, the signals (SIGHUP stops them too) and the console, then the
//! simulator (`crate::sim`) or the demo (`crate::demo`).

use super::exit;
use super::signals::{self, Stops};
use anyhow::Context as _;
use std::process::ExitCode;
use tokio_util::sync::CancellationToken;

pub(crate) use crate::sim::options::SimArgs;

/// The simulator's log level: as asked, else `info` headless and `warn` under the
/// console, so packets do not scroll over the prompt.
fn sim_level(device: &crate::sim::options::DeviceArgs) -> (String, bool) {
    let console = !device.headless && std::io::IsTerminal::is_terminal(&std::io::stdin());
    let level = device
        .log_level
        .clone()
        .unwrap_or_else(|| if console { "warn" } else { "info" }.into());
    (level, console)
}

/// `mbgate sim`: bad options exit 2, a lost port is reopened, SIGTERM stops.
pub(crate) fn sim(args: crate::sim::options::SimArgs) -> ExitCode {
    use crate::sim::serve::{self, Port};
    // Checked by `settings()` too, whose error is the one reported.
    let port = args.serial_config();
    let cie_m10 = args.device.profile == crate::sim::options::ProfileName::CieM10
        && args.replay.replay.is_empty();
    let polling = args.role.polling(cie_m10, args.listen.is_some());
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
        // `--replay FILE --summary`: what the files hold, and no more.
        return match settings {
            Ok(s) => {
                if let crate::sim::Profile::Replay(r) = &s.device.profile {
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
                let listener = crate::sim::tcp::bind(addr)
                    .await
                    .with_context(|| format!("cannot listen on {addr}"))?;
                let n = usize::from(n);
                crate::sim::tcp::run(settings.device, listener, n, commands, shutdown).await?;
                return Ok(());
            }
            let port = match listen {
                Some(addr) => Port::Listen(addr),
                None => Port::Path(port.map_err(anyhow::Error::msg)?),
            };
            match polling.map_err(anyhow::Error::msg)? {
                Some(p) => {
                    crate::sim::master::run(settings, p, port, commands, shutdown).await?;
                }
                None => serve::run(settings, port, commands, shutdown).await?,
            }
            Ok(())
        },
    )
}

/// `mbgate demo`.
pub(crate) fn demo(args: crate::demo::DemoArgs) -> ExitCode {
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
            let stats = crate::demo::run(&args, settings, commands, shutdown, banner_shown).await?;
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
fn master_demo(args: crate::demo::DemoArgs) -> ExitCode {
    let device = args.device.clone();
    let (banner_shown, after_banner) = std::sync::mpsc::channel();
    let settings = args.settings().and_then(|s| match s.device.profile {
        crate::sim::Profile::CieM10(_) => Ok(s),
        crate::sim::Profile::Generic(_) | crate::sim::Profile::Replay(_) => {
            Err("--master is the cie-m10 profile's".into())
        }
    });
    simulate(
        &device,
        settings,
        args.traffic,
        Some(after_banner),
        |settings, commands, shutdown| async move {
            crate::demo::master::run(&args, settings, commands, shutdown, banner_shown).await?;
            Ok(())
        },
    )
}

/// What `sim` and `demo` share: the device options (exit 2 when bad), tracing, the
/// runtime, the signals and the console (shown once `console_after` says so, if given);
/// `body` runs the simulator.
fn simulate<F, Fut>(
    device: &crate::sim::options::DeviceArgs,
    settings: Result<crate::sim::options::Settings, crate::sim::options::BadFlags>,
    traffic: bool,
    console_after: Option<std::sync::mpsc::Receiver<()>>,
    body: F,
) -> ExitCode
where
    F: FnOnce(
        crate::sim::options::Settings,
        tokio::sync::mpsc::Receiver<crate::sim::serve::ConsoleRequest>,
        CancellationToken,
    ) -> Fut,
    Fut: std::future::Future<Output = anyhow::Result<()>>,
{
    let settings = match settings {
        Ok(s) => s,
        Err(e) => {
            eprintln!("mbgate: {e}");
            return exit::code(exit::USAGE);
        }
    };
    let (level, console) = sim_level(device);
    crate::logging::init(&crate::config::LogConfig { level, traffic });
    let rt = match signals::runtime(exit::FAILED) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    finish(rt.block_on(async {
        let shutdown = signals::stop_on(Stops::TermIntHup);
        let commands = crate::sim::terminal::start(console, shutdown.clone(), console_after);
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

/// The end of a simulator's run: 0, or the error and 1.
fn finish(result: anyhow::Result<()>) -> ExitCode {
    match result {
        Ok(()) => exit::code(exit::OK),
        Err(e) => exit::failed(format_args!("{e:#}")),
    }
}
