//! One route's connection to its Modbus/TCP slave, as a task: made by mbgate and
//! remade with backoff when lost (active), or awaited on a listening socket (passive,
//! the slave connects in; a newer connection replaces an older one). TCP keepalive on,
//! Nagle off. It tells the loop when the connection is up or down and hands it each
//! MBAP frame the slave sends; it writes what the loop gives it.

use crate::access::allow::{RefusedLog, Tell};
use crate::config::master::{Peer, Route};
use crate::frame::mbap::decode_strict;
use crate::frame::Adu;
use crate::line::port::Backoff;
use crate::ops::capture::packet::{Dir, Ends, Packet, Part, Proto};
use crate::ops::capture::Tap;
use std::net::SocketAddr;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

/// What a connection task tells the loop, with its route's index.
#[derive(Debug)]
pub(crate) enum SlaveEvent {
    Connecting(usize),
    Up(usize),
    Down(usize),
    Frame(usize, Adu),
}

/// Keepalive probes after this much idleness, then every few seconds: a slave that
/// vanished without a word (power cut, cable) is noticed without a request.
const KEEPALIVE_IDLE: Duration = Duration::from_secs(10);
const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(5);
/// Reconnection delays: from this, doubling, up to the longest.
const RECONNECT_MIN: Duration = Duration::from_millis(100);
const RECONNECT_MAX: Duration = Duration::from_secs(2);
/// Events the routes' tasks may have waiting for the line's loop, all routes
/// together: past it a slave's frames wait in its socket (TCP pushes back).
pub(crate) const EVENTS: usize = 64;

/// A passive route's gate: is the slave connecting from `from` taken? One from
/// outside the route's `allow` list is closed before a byte of it is read (so it can
/// neither answer the serial master's requests nor replace the slave connected),
/// and said at most once a minute per source, with the count in between.
fn admitted(route: &Route, i: usize, from: SocketAddr, refused: &mut RefusedLog) -> bool {
    let Some(allow) = &route.allow else {
        return true;
    };
    let ip = from.ip().to_canonical();
    if allow.allows(ip) {
        return true;
    }
    match refused.refused(ip, Instant::now()) {
        Tell::Quiet => {}
        Tell::Source { more } => warn!(
            route = i,
            "slave connection refused: {ip} is not in the route's allow list ({more} more from it since last said)"
        ),
        Tell::Others { count } => warn!(
            route = i,
            "slave connections refused from {count} sources not in the route's allow list"
        ),
    }
    false
}

fn tune(stream: &TcpStream) {
    let _ = stream.set_nodelay(true);
    let keepalive = socket2::TcpKeepalive::new()
        .with_time(KEEPALIVE_IDLE)
        .with_interval(KEEPALIVE_INTERVAL);
    if let Err(e) = socket2::SockRef::from(stream).set_tcp_keepalive(&keepalive) {
        debug!("cannot set TCP keepalive: {e}");
    }
}

/// Binds a passive route's address (before the line starts, so a taken port is an
/// error at start).
pub(crate) async fn bind(route: &Route) -> std::io::Result<Option<TcpListener>> {
    match &route.peer {
        Peer::Listen(addr) => TcpListener::bind(addr).await.map(Some),
        Peer::Connect(_) => Ok(None),
    }
}

/// Runs route `i`'s connection until `shutdown`: frames to write come on `frames`,
/// events go to `events`; both go to `tap` for the capture.
pub(crate) async fn run(
    i: usize,
    route: Route,
    listener: Option<TcpListener>,
    mut frames: mpsc::UnboundedReceiver<Adu>,
    events: mpsc::Sender<SlaveEvent>,
    (tap, shutdown): (Tap, CancellationToken),
) {
    let mut backoff = Backoff::new(RECONNECT_MIN, RECONNECT_MAX);
    let timeout = Duration::from_millis(route.response_timeout_ms);
    let mut reported = false;
    let mut next: Option<TcpStream> = None;
    let mut refused = RefusedLog::default();
    if listener.is_some() {
        // No slave until one connects in: requests get 0x0A at once meanwhile.
        let _ = events.send(SlaveEvent::Down(i)).await;
    }
    loop {
        let got = match (&listener, &route.peer) {
            (Some(_), _) if next.is_some() => SlaveConnect::Stream(next.take().expect("seen")),
            (Some(l), _) => accept_slave(l, &route, i, &mut refused, &shutdown).await,
            (None, Peer::Connect(addr)) => {
                let tries = (&mut backoff, &mut reported);
                connect_slave(i, addr, timeout, tries, &events, &shutdown).await
            }
            (None, Peer::Listen(_)) => unreachable!("a passive route is bound before it runs"),
        };
        let stream = match got {
            SlaveConnect::Stream(s) => s,
            SlaveConnect::Again => continue,
            SlaveConnect::Stop => return,
        };
        up(i, &stream, &mut frames, &events).await;
        let end = session(
            i,
            stream,
            listener.as_ref().map(|l| (l, &route, &mut refused)),
            (&mut frames, &events),
            &tap,
            &shutdown,
        )
        .await;
        let _ = events.send(SlaveEvent::Down(i)).await;
        match end {
            SlaveEnd::Shutdown => return,
            SlaveEnd::Replaced(s) => next = Some(s),
            SlaveEnd::Lost(why) => {
                warn!(route = i, "slave connection lost ({why})");
                if listener.is_none() {
                    tokio::select! {
                        _ = shutdown.cancelled() => return,
                        _ = tokio::time::sleep(backoff.next_delay()) => {}
                    }
                }
            }
        }
    }
}

/// The slave connected: the connection tuned, the route up.
async fn up(
    i: usize,
    stream: &TcpStream,
    frames: &mut mpsc::UnboundedReceiver<Adu>,
    events: &mpsc::Sender<SlaveEvent>,
) {
    tune(stream);
    // Frames given for a connection that is gone were answered when it went.
    while frames.try_recv().is_ok() {}
    let _ = events.send(SlaveEvent::Up(i)).await;
}

/// What a wait for the slave's connection gave.
enum SlaveConnect {
    Stream(TcpStream),
    /// Nothing yet: wait again.
    Again,
    /// Shutdown.
    Stop,
}

/// A passive route: the next slave that connects in and is admitted.
async fn accept_slave(
    l: &TcpListener,
    route: &Route,
    i: usize,
    refused: &mut RefusedLog,
    shutdown: &CancellationToken,
) -> SlaveConnect {
    tokio::select! {
        _ = shutdown.cancelled() => SlaveConnect::Stop,
        r = l.accept() => match r {
            Ok((_, from)) if !admitted(route, i, from, refused) => SlaveConnect::Again,
            Ok((s, from)) => {
                info!(route = i, "slave connected from {from}");
                SlaveConnect::Stream(s)
            }
            Err(e) => {
                warn!(route = i, "accept: {e}");
                tokio::time::sleep(RECONNECT_MIN).await;
                SlaveConnect::Again
            }
        },
    }
}

/// An active route: a connection to the slave at `addr`, within `timeout`; on failure
/// the route is down until the backoff's next try (the first failure of a run said in
/// the log, `reported`).
async fn connect_slave(
    i: usize,
    addr: &str,
    timeout: Duration,
    (backoff, reported): (&mut Backoff, &mut bool),
    events: &mpsc::Sender<SlaveEvent>,
    shutdown: &CancellationToken,
) -> SlaveConnect {
    let _ = events.send(SlaveEvent::Connecting(i)).await;
    let attempt = tokio::time::timeout(timeout, TcpStream::connect(addr));
    let made = tokio::select! {
        _ = shutdown.cancelled() => return SlaveConnect::Stop,
        r = attempt => r.unwrap_or_else(|_| Err(std::io::ErrorKind::TimedOut.into())),
    };
    match made {
        Ok(s) => {
            backoff.reset();
            *reported = false;
            info!(route = i, "connected to the slave at {addr}");
            SlaveConnect::Stream(s)
        }
        Err(e) => {
            if !*reported {
                warn!(
                    route = i,
                    "cannot reach the slave at {addr} ({e}); retrying"
                );
                *reported = true;
            }
            let _ = events.send(SlaveEvent::Down(i)).await;
            let wait = backoff.next_delay();
            tokio::select! {
                _ = shutdown.cancelled() => SlaveConnect::Stop,
                _ = tokio::time::sleep(wait) => SlaveConnect::Again,
            }
        }
    }
}

enum SlaveEnd {
    Shutdown,
    Lost(String),
    /// A passive route's slave connected again: the new connection replaces this one.
    Replaced(TcpStream),
}

/// A frame to or from the slave (mbgate is the client), for the capture.
fn captured(tap: &Tap, ends: Option<Ends>, adu: &Adu, dir: Dir) {
    if !tap.on() {
        return;
    }
    let (role, label) = match dir {
        Dir::Out => (Part::Query, "gw->slave"),
        _ => (Part::Reply, "slave->gw"),
    };
    let mut p = Packet::new(dir, role, Proto::Mbtcp, adu.as_bytes().to_vec());
    p.ends = ends;
    p.unit = Some(adu.unit());
    p.function = Some(adu.function());
    p.span = crate::line::relay::span(adu.pdu());
    p.label = label;
    tap.send(p, tokio::time::Instant::now());
}

async fn session(
    i: usize,
    stream: TcpStream,
    mut listener: Option<(&TcpListener, &Route, &mut RefusedLog)>,
    (frames, events): (&mut mpsc::UnboundedReceiver<Adu>, &mpsc::Sender<SlaveEvent>),
    tap: &Tap,
    shutdown: &CancellationToken,
) -> SlaveEnd {
    let ends = match (stream.local_addr(), stream.peer_addr()) {
        (Ok(client), Ok(server)) => Some(Ends { client, server }),
        _ => None,
    };
    let (mut rd, mut wr) = stream.into_split();
    let mut buf = bytes::BytesMut::with_capacity(1024);
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => return SlaveEnd::Shutdown,
            r = rd.read_buf(&mut buf) => match r {
                Ok(0) => return SlaveEnd::Lost("closed by the slave".into()),
                Ok(_) => loop {
                    match decode_strict(&mut buf) {
                        Ok(Some(adu)) => {
                            captured(tap, ends, &adu, Dir::In);
                            // Awaited: a slave that sends faster than the loop takes
                            // its frames (the serial port held by flow control) is
                            // pushed back on TCP, never queued without bound.
                            let _ = events.send(SlaveEvent::Frame(i, adu)).await;
                        }
                        Ok(None) => break,
                        Err(e) => return SlaveEnd::Lost(format!("not Modbus/TCP: {e}")),
                    }
                },
                Err(e) => return SlaveEnd::Lost(e.to_string()),
            },
            Some(adu) = frames.recv() => {
                captured(tap, ends, &adu, Dir::Out);
                if let Err(e) = wr.write_all(adu.as_bytes()).await {
                    return SlaveEnd::Lost(e.to_string());
                }
            }
            r = async { listener.as_ref().expect("guarded").0.accept().await }, if listener.is_some() => {
                let Some((_, route, refused)) = listener.as_mut() else { continue };
                if let Ok((s, from)) = r {
                    if admitted(route, i, from, refused) {
                        info!(route = i, "slave connected again from {from}; the new connection replaces the old");
                        return SlaveEnd::Replaced(s);
                    }
                }
            }
        }
    }
}
