//! An in-memory pipe as a [`Port`] (`tokio::io::duplex`): each open hands the far end
//! to a [`DeviceEnd`], so a device written in Rust can sit on the other side of the
//! relay in a test; a small pipe capacity stands in for flow control holding writes
//! back, dropping the far end for a port that is lost. With a switch
//! ([`DuplexPort::with_switch`]) the pipe is a half-duplex bus: what the relay writes
//! while its transmitter is off never reaches the device, as on RS-485.

use super::serial::direction::{Switch, Transmitter};
use super::{OpenPort, Opening, Port};
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncWrite, DuplexStream};
use tokio::sync::mpsc;

/// Makes the transmitter's switch at each open.
pub(crate) type SwitchMaker = Arc<dyn Fn() -> Box<dyn Switch> + Send + Sync>;

/// A switch of the in-memory bus: `on` is the transmitter, which its switch must set.
pub struct Bus {
    /// The switch at each open, which must keep `on` as it switches.
    pub make: SwitchMaker,
    /// The transmitter is on.
    pub on: Arc<AtomicBool>,
    /// Bytes the relay wrote while it was off: lost on the bus.
    pub lost: Arc<AtomicU64>,
}

impl std::fmt::Debug for Bus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bus")
            .field("on", &self.on)
            .field("lost", &self.lost)
            .finish()
    }
}

/// The relay's side: opens a fresh pipe each time.
#[derive(Debug)]
pub struct DuplexPort {
    capacity: usize,
    char_time: Duration,
    ends: mpsc::UnboundedSender<DuplexStream>,
    refuse: Arc<AtomicBool>,
    bus: Option<Arc<Bus>>,
}

/// The device's side: receives the far end of each pipe the relay opens.
#[derive(Debug)]
pub struct DeviceEnd {
    ends: mpsc::UnboundedReceiver<DuplexStream>,
    refuse: Arc<AtomicBool>,
}

/// A port whose pipes hold `capacity` bytes each way (a writer waits while its pipe is
/// full, as a serial port does while CTS is low), whose bytes take `char_time` each on
/// the wire (for the relay's timing; the pipe itself is instant), and the device end.
pub fn pair(capacity: usize, char_time: Duration) -> (DuplexPort, DeviceEnd) {
    let (tx, rx) = mpsc::unbounded_channel();
    let refuse = Arc::new(AtomicBool::new(false));
    (
        DuplexPort {
            capacity,
            char_time,
            ends: tx,
            refuse: refuse.clone(),
            bus: None,
        },
        DeviceEnd { ends: rx, refuse },
    )
}

impl DeviceEnd {
    /// The far end of the next pipe the relay opens.
    pub async fn accept(&mut self) -> DuplexStream {
        self.ends
            .recv()
            .await
            .expect("the port lives as long as the relay")
    }

    /// While `refuse` is true, opens fail (the device is unplugged).
    pub fn refuse_opens(&self, refuse: bool) {
        self.refuse.store(refuse, Ordering::SeqCst);
    }
}

impl DuplexPort {
    /// The pipe as a half-duplex bus whose transmitter `bus` switches: the relay's
    /// bytes written while it is off are lost (and counted).
    pub fn with_switch(mut self, bus: Bus) -> DuplexPort {
        self.bus = Some(Arc::new(bus));
        self
    }
}

/// The relay's writing half on a bus: bytes written while the transmitter is off
/// are taken and lost.
struct Gated<W> {
    inner: W,
    bus: Arc<Bus>,
}

impl<W: AsyncWrite + Unpin> AsyncWrite for Gated<W> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        if !self.bus.on.load(Ordering::SeqCst) {
            self.bus.lost.fetch_add(buf.len() as u64, Ordering::SeqCst);
            return Poll::Ready(Ok(buf.len()));
        }
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }
    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }
    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

impl Port for DuplexPort {
    fn kind(&self) -> &'static str {
        "in-memory port"
    }

    fn name(&self) -> &str {
        "duplex"
    }

    fn open(&mut self) -> Opening {
        let opened = if self.refuse.load(Ordering::SeqCst) {
            Err(io::Error::new(
                io::ErrorKind::NotFound,
                "refused by the test",
            ))
        } else {
            let (near, far) = tokio::io::duplex(self.capacity);
            match self.ends.send(far) {
                Ok(()) => Ok(near),
                Err(_) => Err(io::Error::new(io::ErrorKind::NotFound, "no device end")),
            }
        };
        let bus = self.bus.clone();
        Box::pin(async move {
            let (reader, writer) = tokio::io::split(opened?);
            let (writer, transmitter): (super::Writer, _) = match bus {
                Some(bus) => {
                    let switch = Transmitter::new((bus.make)())?;
                    (Box::new(Gated { inner: writer, bus }), Some(switch))
                }
                None => (Box::new(writer), None),
            };
            Ok(OpenPort {
                reader: Box::new(reader),
                writer,
                control: Box::new(Pipe(transmitter)),
                info: super::kind::PortInfo::plain(super::kind::Medium::Memory),
            })
        })
    }

    fn wire_time(&self, bytes: usize) -> Duration {
        self.char_time * u32::try_from(bytes).unwrap_or(u32::MAX)
    }
}

/// Drained at once: the pipe has no wire; the bus's switch, if it is one.
struct Pipe(Option<Transmitter>);

impl super::Control for Pipe {
    fn transmit(&mut self, on: bool) -> io::Result<()> {
        match &mut self.0 {
            Some(t) => t.set(on),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::port::open_now;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    #[tokio::test]
    async fn opens_at_once_hands_the_far_end_over_and_refuses_on_demand() {
        let (mut port, mut device) = pair(64, Duration::from_micros(100));
        assert_eq!(port.wire_time(10), Duration::from_millis(1));
        let mut link = open_now(port.open()).ok().expect("ready").unwrap();
        let mut far = device.accept().await;
        link.writer.write_all(b"ping").await.unwrap();
        let mut got = [0u8; 4];
        far.read_exact(&mut got).await.unwrap();
        assert_eq!(&got, b"ping");
        drop(far);
        assert_eq!(link.reader.read(&mut got).await.unwrap(), 0, "lost");

        device.refuse_opens(true);
        let refused = open_now(port.open()).ok().expect("ready");
        assert!(refused.is_err());
        device.refuse_opens(false);
        assert!(open_now(port.open()).ok().expect("ready").is_ok());
    }
}
