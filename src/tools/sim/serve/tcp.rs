//! `mbgate sim --listen ADDR`: the simulated device on the network, as the devices a
//! TCP line is for (docs/network-devices.md): a Modbus/TCP slave (MBAP
//! framing) or a serial device server in raw TCP mode (RTU or ASCII framing) that
//! serves one connection at a time. A second connection while one is served is
//! accepted and closed at once, as such devices do.

use super::{ConsoleRequest, SessionEnd, Sim, SimError};
use std::net::SocketAddr;
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

/// Serves connections on `addr`, one at a time, until shutdown.
pub(super) async fn listen(
    sim: &mut Sim,
    addr: SocketAddr,
    commands: &mut mpsc::Receiver<ConsoleRequest>,
    mut ticks: Option<tokio::time::Interval>,
    shutdown: &CancellationToken,
) -> Result<(), SimError> {
    let listener = TcpListener::bind(addr).await.map_err(SimError::Lost)?;
    let local = listener.local_addr().map_err(SimError::Lost)?;
    info!(
        "simulating {} on tcp {local}, one connection at a time",
        sim.describe()
    );
    loop {
        let (mut stream, peer) = tokio::select! {
            _ = shutdown.cancelled() => return Ok(()),
            Some(req) = commands.recv() => {
                sim.command(req);
                continue;
            }
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                Err(e) => {
                    warn!("accept failed: {e}");
                    continue;
                }
            },
        };
        let _ = stream.set_nodelay(true);
        info!(%peer, "connected");
        let end = {
            let serving = sim.serve(&mut stream, commands, ticks.as_mut(), shutdown);
            tokio::pin!(serving);
            loop {
                tokio::select! {
                    end = &mut serving => break end,
                    Ok((second, other)) = listener.accept() => {
                        warn!(peer = %other, "a second connection closed: one at a time");
                        drop(second);
                    }
                }
            }
        };
        match end {
            SessionEnd::Shutdown => return Ok(()),
            SessionEnd::Lost(e) => {
                info!(%peer, "disconnected ({e}); waiting for the next connection")
            }
        }
    }
}
