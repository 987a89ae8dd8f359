//! The UDP listeners running, as a reload finds them (docs/dialing.md "Reload"): one
//! adopted at start, and at each reload the file's started, stopped or started again
//! on its own socket with new settings.

use super::{bind, datagram_loop};
use crate::config::{ListenConfig, Transport};
use crate::masters::tcp::tally::SourceTally;
use crate::masters::tcp::{Listening, Shared};
use std::sync::Arc;
use tokio::net::UdpSocket;

/// The UDP listeners running, as a reload finds them (docs/dialing.md "Reload"):
/// each its configuration, its socket, the token that stops it and its counters.
pub(crate) struct Udps {
    shared: Shared,
    tally: Arc<SourceTally>,
    running: Vec<RunningUdp>,
}

struct RunningUdp {
    listen: ListenConfig,
    socket: Arc<UdpSocket>,
    stop: tokio_util::sync::CancellationToken,
    stats: Arc<crate::ops::stats::Stats>,
}

impl Udps {
    pub(crate) fn new(shared: Shared, tally: Arc<SourceTally>) -> Udps {
        Udps {
            shared,
            tally,
            running: Vec::new(),
        }
    }

    /// A UDP listener bound at start, served from now on with its counters `stats`.
    pub(crate) fn adopt(
        &mut self,
        socket: UdpSocket,
        listening: Listening,
        stats: Arc<crate::ops::stats::Stats>,
    ) {
        let listen = listening.listen.clone();
        let socket = Arc::new(socket);
        let stop = self.start(socket.clone(), listening, stats.clone());
        self.running.push(RunningUdp {
            listen,
            socket,
            stop,
            stats,
        });
    }

    fn start(
        &self,
        socket: Arc<UdpSocket>,
        listening: Listening,
        stats: Arc<crate::ops::stats::Stats>,
    ) -> tokio_util::sync::CancellationToken {
        // Its own stop, for a reload; its sources' writers see the gateway's shutdown.
        let stop = self.shared.shutdown.child_token();
        let shared = Shared {
            stats,
            ..self.shared.clone()
        };
        self.shared
            .tracker
            .spawn(datagram_loop(socket, listening, shared, stop.clone()));
        stop
    }

    /// The UDP listeners of `listeners` running, and no other: one unchanged keeps
    /// its sources, one new is bound and started, one gone stops, one changed starts
    /// again with its new settings on the same socket (its sources begin anew). One
    /// gone leaves the metrics, its counts staying in the totals. What it did, in words (a listener that cannot be bound is said and left out).
    pub(crate) fn apply(&mut self, listeners: &[ListenConfig]) -> Vec<String> {
        let mut said = Vec::new();
        let mut old = std::mem::take(&mut self.running);
        let udp = listeners.iter().filter(|l| l.transport == Transport::Udp);
        for (i, l) in udp.enumerate() {
            if let Some(p) = old.iter().position(|r| r.listen == *l) {
                self.running.push(old.remove(p));
                continue;
            }
            let name = format!("udp[{i}]");
            let same_address = old.iter().position(|r| r.listen.tcp.listen == l.tcp.listen);
            let (socket, stats) = match same_address {
                Some(p) => {
                    let r = old.remove(p);
                    r.stop.cancel();
                    (r.socket, r.stats)
                }
                None => match bind(l.tcp.listen) {
                    Ok(s) => (Arc::new(s), self.tally.open(l.tcp.listen.to_string())),
                    Err(e) => {
                        said.push(format!("cannot listen on {} (UDP): {e}", l.tcp.listen));
                        continue;
                    }
                },
            };
            let local = socket.local_addr().unwrap_or(l.tcp.listen);
            tracing::info!("listening on {local} (UDP) for Modbus/UDP masters");
            let listening = Listening {
                listen: l.clone(),
                name,
                local,
                tls: None,
            };
            let stop = self.start(socket.clone(), listening, stats.clone());
            self.running.push(RunningUdp {
                listen: l.clone(),
                socket,
                stop,
                stats,
            });
        }
        for r in old {
            r.stop.cancel();
            self.tally.close(&r.stats);
        }
        said
    }
}
