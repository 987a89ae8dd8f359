//! A device behind a TCP socket as a [`Port`] (a Modbus/TCP slave, or a serial device
//! server in raw TCP mode): connected without blocking the loop, within a bounded
//! time, Nagle off so a request leaves whole, TCP keepalive on so a device that
//! vanished without a word (power cut, cable pulled) is noticed and reconnected.

use super::{Link, Opening, Port};
use socket2::{SockRef, TcpKeepalive};
use std::time::Duration;

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
}

impl TcpPort {
    /// The device at `addr` (`host:port`); nothing is connected yet.
    pub(crate) fn new(addr: impl Into<String>) -> Self {
        Self { addr: addr.into() }
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
        Box::pin(async move {
            let connect = tokio::net::TcpStream::connect(&addr);
            let stream = match tokio::time::timeout(CONNECT_TIMEOUT, connect).await {
                Ok(connected) => connected?,
                Err(_) => {
                    let m = format!("no connection within {CONNECT_TIMEOUT:?}");
                    return Err(std::io::Error::new(std::io::ErrorKind::TimedOut, m));
                }
            };
            stream.set_nodelay(true)?;
            let keepalive = TcpKeepalive::new()
                .with_time(KEEPALIVE_IDLE)
                .with_interval(KEEPALIVE_EVERY)
                .with_retries(KEEPALIVE_PROBES);
            SockRef::from(&stream).set_tcp_keepalive(&keepalive)?;
            let (reader, writer) = stream.into_split();
            Ok(Link {
                info: super::kind::PortInfo::plain(super::kind::Kind::Tcp),
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
