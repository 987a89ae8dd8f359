//! A device behind a TCP socket as a [`Port`] (a Modbus/TCP slave, or a serial device
//! server in raw TCP mode): connected without blocking the loop, within a bounded
//! time, Nagle off so a request leaves whole, TCP keepalive on so a device that
//! vanished without a word (power cut, cable pulled) is noticed and reconnected.
//! Over TLS (docs/security.md "A device behind TLS") the handshake is part of the
//! bounded connect, and a task of its own carries the bytes between the TLS stream and
//! the relay, flushing each write, since the relay writes and never flushes.

use super::{OpenPort, Opening, Port};
use crate::config::TlsDevice;
use crate::tls::client::Connector;
use socket2::{SockRef, TcpKeepalive};
use std::time::Duration;
use tokio::io::AsyncWriteExt;

/// How long a connect may take before the attempt counts as failed (and is retried
/// with backoff, masters answered 0x0A meanwhile).
const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);

/// Keepalive: the first probe after this much silence, then every `KEEPALIVE_EVERY`,
/// the connection dropped after `KEEPALIVE_PROBES` unanswered (about 25 s in all,
/// against Linux's default of over two hours).
const KEEPALIVE_IDLE: Duration = Duration::from_secs(10);
const KEEPALIVE_EVERY: Duration = Duration::from_secs(5);
const KEEPALIVE_PROBES: u32 = 3;

/// A device's address on the network.
#[derive(Debug)]
pub(crate) struct TcpPort {
    /// `host:port`: resolved again at each connect, so a device whose name moves to
    /// another address is found there.
    addr: String,
    /// The device speaks TLS: its files are read at each connect.
    tls: Option<TlsDevice>,
}

impl TcpPort {
    /// The device at `addr` (`host:port`); nothing is connected yet.
    pub(crate) fn new(addr: impl Into<String>) -> Self {
        Self {
            addr: addr.into(),
            tls: None,
        }
    }

    /// The device at `addr` behind TLS.
    pub(crate) fn with_tls(mut self, tls: Option<TlsDevice>) -> Self {
        self.tls = tls;
        self
    }
}

/// The room of the in-memory pipe between the relay and a TLS device's task: more than
/// the relay ever has in flight.
const PIPE: usize = 64 * 1024;

/// Carries bytes both ways between the relay's end of a pipe and the TLS stream until
/// either side ends; then the other side is shut down (a TLS `close_notify` to the
/// device, the end of the stream to the relay) and the connection dropped.
async fn carry(
    relay_end: tokio::io::DuplexStream,
    tls: tokio_rustls::client::TlsStream<tokio::net::TcpStream>,
) {
    let (mut from_relay, mut to_relay) = tokio::io::split(relay_end);
    let (mut from_device, mut to_device) = tokio::io::split(tls);
    let up = async {
        let _ = tokio::io::copy(&mut from_relay, &mut to_device).await;
        let _ = to_device.shutdown().await;
    };
    let down = async {
        let _ = tokio::io::copy(&mut from_device, &mut to_relay).await;
        let _ = to_relay.shutdown().await;
    };
    tokio::select! {
        _ = up => {}
        _ = down => {}
    }
}

impl Port for TcpPort {
    fn kind(&self) -> &'static str {
        "device socket"
    }

    fn name(&self) -> &str {
        &self.addr
    }

    fn open(&mut self) -> Opening {
        let addr = self.addr.clone();
        let tls = self.tls.clone();
        Box::pin(async move {
            let connector = match &tls {
                Some(t) => Some(
                    Connector::load(t, &addr, "tcp.tls")
                        .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))?,
                ),
                None => None,
            };
            let deadline = tokio::time::Instant::now() + CONNECT_TIMEOUT;
            let connect = tokio::net::TcpStream::connect(&addr);
            let timed_out = || {
                let m = format!("no connection within {CONNECT_TIMEOUT:?}");
                std::io::Error::new(std::io::ErrorKind::TimedOut, m)
            };
            let stream = match tokio::time::timeout_at(deadline, connect).await {
                Ok(connected) => connected?,
                Err(_) => return Err(timed_out()),
            };
            stream.set_nodelay(true)?;
            let keepalive = TcpKeepalive::new()
                .with_time(KEEPALIVE_IDLE)
                .with_interval(KEEPALIVE_EVERY)
                .with_retries(KEEPALIVE_PROBES);
            SockRef::from(&stream).set_tcp_keepalive(&keepalive)?;
            if let Some(connector) = connector {
                let handshake = connector.connect(stream);
                let tls = match tokio::time::timeout_at(deadline, handshake).await {
                    Ok(done) => done.map_err(|e| {
                        std::io::Error::new(e.kind(), format!("TLS handshake with the device: {e}"))
                    })?,
                    Err(_) => return Err(timed_out()),
                };
                let (relay_end, carried) = tokio::io::duplex(PIPE);
                tokio::spawn(carry(carried, tls));
                let (reader, writer) = tokio::io::split(relay_end);
                return Ok(OpenPort {
                    info: super::kind::PortInfo::plain(super::kind::Medium::Tcp),
                    reader: Box::new(reader),
                    writer: Box::new(writer),
                    control: Box::new(NoControl),
                });
            }
            let (reader, writer) = stream.into_split();
            Ok(OpenPort {
                info: super::kind::PortInfo::plain(super::kind::Medium::Tcp),
                reader: Box::new(reader),
                writer: Box::new(writer),
                control: Box::new(NoControl),
            })
        })
    }

    /// The socket has no line speed of its own: the device server's serial side is
    /// timed by the response timeout.
    fn wire_time(&self, _bytes: usize) -> Duration {
        Duration::ZERO
    }
}

/// Drained at once, input unknown: the kernel's socket buffers say nothing about the
/// device server's serial line.
struct NoControl;

impl super::Control for NoControl {}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    #[tokio::test]
    async fn connects_reads_writes_and_fails_when_nobody_listens() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let mut port = TcpPort::new(addr.to_string());
        assert_eq!(port.name(), addr.to_string());
        let opening = port.open();
        let (link, accepted) = tokio::join!(opening, listener.accept());
        let mut link = link.unwrap();
        let (mut device, _) = accepted.unwrap();
        link.writer.write_all(b"\x00\x01req").await.unwrap();
        let mut got = [0u8; 5];
        device.read_exact(&mut got).await.unwrap();
        assert_eq!(&got, b"\x00\x01req");
        device.write_all(b"reply").await.unwrap();
        let mut got = [0u8; 5];
        link.reader.read_exact(&mut got).await.unwrap();
        assert_eq!(&got, b"reply");
        link.control.drain().unwrap().await.unwrap();
        assert!(!link.control.input_waiting());
        drop(device);
        assert_eq!(
            link.reader.read(&mut got).await.unwrap(),
            0,
            "the far end went away"
        );

        drop(listener);
        let mut gone = TcpPort::new(addr.to_string());
        assert!(gone.open().await.is_err(), "nobody listens there any more");
    }
}
