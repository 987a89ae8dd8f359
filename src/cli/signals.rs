//! The runtime every subcommand runs on and the signals that stop it, set up here
//! once: the one-thread runtime (`crate::cli::runtime`), and which of SIGINT (Ctrl-C),
//! SIGTERM (systemd stop) and SIGHUP start a graceful stop.

use super::exit;
use std::process::ExitCode;
use tokio::runtime::Runtime;
use tokio_util::sync::CancellationToken;

/// The log target of these lines: the program's, as when `main.rs` logged them.
const TARGET: &str = "mbgate";

/// The runtime; when it cannot be had, says so on stderr and gives exit code
/// `failed`, the subcommand's for a failure of its own.
pub(crate) fn runtime(failed: u8) -> Result<Runtime, ExitCode> {
    crate::cli::runtime::new().map_err(|e| {
        eprintln!("mbgate: starting the runtime: {e}");
        exit::code(failed)
    })
}

/// The signals that stop a subcommand gracefully; any other keeps its default action.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Stops {
    /// SIGINT only: `scan`, `read --poll` (a SIGTERM ends them at once).
    Interrupt,
    /// SIGTERM and SIGINT: `run` (whose SIGHUP is a reload, handled by the gateway,
    /// `crate::gateway::reload`), `wire`.
    TermInt,
    /// SIGTERM, SIGINT and SIGHUP: `sim`, `demo`: a closed terminal stops them,
    /// gracefully (SIGHUP's default action would end the process at once).
    TermIntHup,
}

/// Cancels `shutdown` at the first of the signals `stops` names. The handlers are
/// installed before this returns, so a signal that comes at once is not fatal; the
/// future it returns waits for one. Call it inside the runtime.
pub(crate) fn watch(
    shutdown: CancellationToken,
    stops: Stops,
) -> impl std::future::Future<Output = ()> {
    use tokio::signal::unix::{signal, SignalKind};
    let handlers = (
        (stops != Stops::Interrupt).then(|| signal(SignalKind::terminate())),
        signal(SignalKind::interrupt()),
        (stops == Stops::TermIntHup).then(|| signal(SignalKind::hangup())),
    );
    async move {
        let (term, Ok(mut int)) = (handlers.0.transpose(), handlers.1) else {
            tracing::error!(target: TARGET, "cannot install signal handlers");
            return;
        };
        let Ok(mut term) = term else {
            tracing::error!(target: TARGET, "cannot install signal handlers");
            return;
        };
        let mut hup = handlers.2.and_then(Result::ok);
        let terminated = async {
            match &mut term {
                Some(term) => term.recv().await,
                None => std::future::pending().await,
            }
        };
        let hung_up = async {
            match &mut hup {
                Some(hup) => hup.recv().await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = terminated => tracing::info!(target: TARGET, "SIGTERM received"),
            _ = int.recv() => tracing::info!(target: TARGET, "SIGINT received"),
            _ = hung_up => tracing::info!(target: TARGET, "SIGHUP received; stopping"),
        }
        shutdown.cancel();
    }
}

/// Starts [`watch`] on the runtime and gives the token it cancels.
pub(crate) fn stop_on(stops: Stops) -> CancellationToken {
    let shutdown = CancellationToken::new();
    tokio::spawn(watch(shutdown.clone(), stops));
    shutdown
}
