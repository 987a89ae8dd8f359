//! A device behind a TCP socket as a [`Port`] (a serial device server in raw TCP
//! mode): connected without blocking the loop, Nagle off so a request leaves whole.

use super::{Link, Opening, Port};
use std::net::SocketAddr;
use std::time::Duration;

/// A device server's address.
#[derive(Debug)]
pub struct TcpPort {
    addr: SocketAddr,
    name: String,
}

impl TcpPort {
    /// The device at `addr`; nothing is connected yet.
    pub fn new(addr: SocketAddr) -> Self {
        Self {
            addr,
            name: addr.to_string(),
        }
    }
}

impl Port for TcpPort {
    fn kind(&self) -> &'static str {
        "device socket"
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn open(&mut self) -> Opening {
        let addr = self.addr;
        Box::pin(async move {
            let stream = tokio::net::TcpStream::connect(addr).await?;
            stream.set_nodelay(true)?;
            let (reader, writer) = stream.into_split();
            Ok(Link {
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
        let mut port = TcpPort::new(addr);
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
        let mut gone = TcpPort::new(addr);
        assert!(gone.open().await.is_err(), "nobody listens there any more");
    }
}
