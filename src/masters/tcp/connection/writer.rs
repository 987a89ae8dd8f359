//! A master's connection writing: its replies in the order of its requests and the
//! device's notifications as they come, each logged and captured first; a dialed
//! connection's heartbeat on a quiet connection; a master that stops reading its
//! replies closed, never held for ever.

use super::codec::MasterCodec;
use super::{Connection, Ended, Origin};
use crate::frame::hex::Hex;
use crate::line::outbox::{Delivery, Inbox};
use crate::masters::tcp::live::Live;
use crate::ops::capture::packet::Dir;
use std::future::Future;
use std::task::Poll;
use std::time::Duration;
use tokio::io::{AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;
use tracing::{debug, info};

/// Room for the longest frame either framing writes (an MBAP frame of 260 bytes, an
/// RTU one of 256).
const FRAME_ROOM: usize = 260;

/// What a writer keeps from one frame to the next: the buffer each frame is framed in,
/// the configuration as it runs, how long a frame may wait for the socket, and what
/// the master's source adds (`origin`).
struct Writing<'a, O> {
    buf: Vec<u8>,
    live: Live,
    stall: Duration,
    origin: &'a O,
}

impl Connection {
    /// Writes the master's replies in the order of its requests, and notifications as
    /// they come; on a dialed connection with a heartbeat, the heartbeat whenever no
    /// reply was written for its interval. A master that stops reading its replies
    /// for `idle_timeout_ms` is closed, so it cannot hold a connection slot for ever
    /// (a dialed server, for its dial's own bound). Why it stopped.
    pub(in crate::masters::tcp) async fn write_loop<C: MasterCodec, O: Origin>(
        &self,
        origin: &O,
        mut wr: impl AsyncWrite + Unpin,
        mut inbox: Inbox,
    ) -> Ended {
        let dialed = origin.dialed();
        let mut w = Writing {
            buf: Vec::with_capacity(FRAME_ROOM),
            live: Live::new(&self.running),
            stall: match dialed {
                Some(d) => d.stall,
                None => Duration::from_millis(self.listen.tcp.idle_timeout_ms),
            },
            origin,
        };
        let Some(beat) = dialed.filter(|d| !d.heartbeat.is_empty()) else {
            while let Some(out) = inbox.next().await {
                if let Err(why) = self.write_reply::<C, O>(&mut wr, &out, &mut w).await {
                    return why;
                }
                // `out` drops here: a reply's pipelining slot is free again, and the
                // idle clock starts from now.
            }
            return Ended::NoMoreReplies;
        };
        // One timer for the connection's life, moved at each reply and each beat.
        let timer = tokio::time::sleep(beat.every);
        tokio::pin!(timer);
        loop {
            tokio::select! {
                out = inbox.next() => {
                    let Some(out) = out else {
                        return Ended::NoMoreReplies;
                    };
                    if let Err(why) = self.write_reply::<C, O>(&mut wr, &out, &mut w).await {
                        return why;
                    }
                }
                _ = &mut timer => {
                    beat.beat(Instant::now());
                    debug!(conn = self.id, "heartbeat");
                    if let Err(why) = self.write_bytes(&mut wr, &beat.heartbeat, w.stall).await {
                        return why;
                    }
                }
            }
            timer.as_mut().reset(Instant::now() + beat.every);
        }
    }

    /// One reply or notification written (logged, `log.traffic` as the configuration
    /// runs now, and captured first), framed in the writer's buffer; `Err`: why the
    /// connection must close.
    async fn write_reply<C: MasterCodec, O: Origin>(
        &self,
        wr: &mut (impl AsyncWrite + Unpin),
        out: &Delivery,
        w: &mut Writing<'_, O>,
    ) -> Result<(), Ended> {
        if w.live.get().log.traffic {
            debug!(target: "mbgate::traffic", dir = "gw->master", conn = self.id, "{}", Hex(out.adu().as_bytes()));
        }
        if self.tap.on() {
            self.captured::<C>(&out.adu(), Dir::Out, "gw->master");
        }
        if !C::answers(out.unit()) {
            debug!(
                conn = self.id,
                "answer to a broadcast (unit 0): not written"
            );
            return Ok(());
        }
        w.buf.clear();
        C::frame_into(out.frame(), out.tid(), out.unit(), &mut w.buf);
        self.write_bytes(wr, &w.buf, w.stall).await?;
        if let Some(d) = w.origin.dialed() {
            // A write's reply reads as the write: a server echoing it straight back
            // must not have it run again (`reflect::Loops::came_back`).
            d.replied(&w.buf, out.frame().pdu(), Instant::now());
        }
        Ok(())
    }

    /// `frame` written and flushed, within `stall` (none: 0) if the socket cannot take
    /// it at once.
    async fn write_bytes(
        &self,
        wr: &mut (impl AsyncWrite + Unpin),
        frame: &[u8],
        stall: Duration,
    ) -> Result<(), Ended> {
        // Flushed: a TLS stream holds what it could not send at once until then.
        let write = async {
            wr.write_all(frame).await?;
            wr.flush().await
        };
        let mut write = std::pin::pin!(write);
        // Nearly every reply goes out at once, and needs no timer (each would read
        // the clock): the stall's timer starts only for one the socket cannot take.
        let first = std::future::poll_fn(|cx| Poll::Ready(write.as_mut().poll(cx))).await;
        let result = match first {
            Poll::Ready(r) => r,
            Poll::Pending if stall.is_zero() => write.await,
            Poll::Pending => match tokio::time::timeout(stall, write).await {
                Ok(r) => r,
                Err(_) => {
                    info!(conn = self.id, peer = %self.peer, "master stopped reading its replies; closing the connection");
                    return Err(Ended::Stalled);
                }
            },
        };
        result.map_err(|e| {
            debug!(conn = self.id, "write failed: {e}");
            Ended::Write(e)
        })
    }
}
