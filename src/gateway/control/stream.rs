//! A capture streamed to a client of the control socket (docs/capture.md): the
//! pcapng header, the packets in messages of up to `MESSAGE_SOFT` bytes, and the end
//! with each interface's statistics and the drops.

use super::serve::write_within;
use super::{message, DATA, END};
use crate::ops::capture::hub::{unix_us, Hub, Subscription, GATHER};
use crate::ops::capture::packet::Packet;
use crate::ops::capture::pcapng;
use crate::ops::capture::request::CaptureRequest;
use std::time::Duration;
use tokio::io::AsyncReadExt;
use tokio::net::unix::{OwnedReadHalf, OwnedWriteHalf};
use tokio::time::Instant;

/// A capture's message of packets is sent once it holds this many bytes (and at each
/// gathering): a message is never much longer, so the client's bound on one
/// (`capture.rs` `MAX_MESSAGE`) is far above any the gateway sends.
const MESSAGE_SOFT: usize = 1 << 20;

/// A capture running for one client of the control socket.
pub(super) struct CaptureRun {
    pub(super) sub: Subscription,
    pub(super) request: CaptureRequest,
    pub(super) packets: u64,
    /// Packets written, by interface.
    pub(super) written: Vec<u64>,
    pub(super) start_us: u64,
}

impl CaptureRun {
    /// Adds `p` to `blocks`, unless the count is reached already: whether it did.
    fn take(&mut self, p: &Packet, blocks: &mut Vec<u8>) -> bool {
        if self.counted() {
            return false;
        }
        self.written[usize::from(p.iface)] += 1;
        self.packets += 1;
        blocks.extend(p.block(u32::from(p.iface)));
        true
    }

    /// Has the capture its `--count`?
    fn counted(&self) -> bool {
        self.request.count.is_some_and(|n| self.packets >= n)
    }

    /// `blocks` as one message to `wr` (none when empty), emptied.
    async fn send(
        &self,
        wr: &mut OwnedWriteHalf,
        blocks: &mut Vec<u8>,
    ) -> Result<(), &'static str> {
        if blocks.is_empty() {
            return Ok(());
        }
        let mut msg = Vec::with_capacity(blocks.len() + 5);
        message(&mut msg, DATA, blocks);
        blocks.clear();
        write_within(wr, &msg).await
    }

    /// Streams the capture to `wr`; returns why it ended.
    pub(super) async fn stream(
        &mut self,
        rd: &mut OwnedReadHalf,
        wr: &mut OwnedWriteHalf,
        hub: &Hub,
    ) -> &'static str {
        let mut head = pcapng::section_header(&format!("mbgate {}", env!("CARGO_PKG_VERSION")));
        for i in hub.interfaces() {
            head.extend(pcapng::interface(&i.name, &i.description));
        }
        let mut out = b"ok\n".to_vec();
        message(&mut out, DATA, &head);
        if let Err(why) = write_within(wr, &out).await {
            return why;
        }
        // Bounded by the request's reader (a year at most); checked all the same.
        let until = self
            .request
            .seconds
            .and_then(|s| Instant::now().checked_add(Duration::from_secs(s)));
        let mut cmd = [0u8; 64];
        let why = loop {
            let mut blocks = Vec::new();
            let ended = tokio::select! {
                p = self.sub.rx.recv() => match p {
                    None => Some("the gateway stopped"),
                    Some(p) => {
                        self.take(&p, &mut blocks);
                        None
                    }
                },
                r = rd.read(&mut cmd) => match r {
                    Ok(0) | Err(_) => return "the client went away",
                    // `stop`, or anything else: the client wants no more.
                    Ok(_) => Some("stopped"),
                },
                _ = async { tokio::time::sleep_until(until.expect("guarded")).await }, if until.is_some() => {
                    Some("seconds")
                }
            };
            if let Some(why) = ended {
                if let Err(why) = self.last(wr, &mut blocks).await {
                    return why;
                }
                break why;
            }
            if let Err(why) = self.waiting(wr, &mut blocks).await {
                return why;
            }
            if self.counted() {
                break "count";
            }
            // Packets gather meanwhile: one wake and one write for many.
            tokio::select! {
                _ = tokio::time::sleep(GATHER) => {}
                _ = hub.closed() => {}
            }
        };
        self.end(wr, why).await
    }

    /// Stopped, or the time is up: what the gateway handed to this capture before then
    /// is written too, and nothing after it; the drops counted so far are the final
    /// count.
    async fn last(
        &mut self,
        wr: &mut OwnedWriteHalf,
        blocks: &mut Vec<u8>,
    ) -> Result<(), &'static str> {
        self.sub.detach();
        while !self.counted() {
            let Some(p) = self.sub.rx.recv().await else {
                break;
            };
            self.take(&p, blocks);
            if blocks.len() >= MESSAGE_SOFT {
                self.send(wr, blocks).await?;
            }
        }
        self.send(wr, blocks).await
    }

    /// Whatever else is waiting goes in the same message (or a few, past
    /// MESSAGE_SOFT). A gateway that stops ends the capture when its last packet (the
    /// drain's answers included) has gone out: the hub closes, `recv` gives `None`.
    async fn waiting(
        &mut self,
        wr: &mut OwnedWriteHalf,
        blocks: &mut Vec<u8>,
    ) -> Result<(), &'static str> {
        while !self.counted() {
            let Ok(p) = self.sub.rx.try_recv() else {
                break;
            };
            self.take(&p, blocks);
            if blocks.len() >= MESSAGE_SOFT {
                self.send(wr, blocks).await?;
            }
        }
        self.send(wr, blocks).await
    }

    /// The capture's end: each interface's statistics, then the end message with the
    /// packets, the drops and `why`.
    async fn end(&self, wr: &mut OwnedWriteHalf, why: &'static str) -> &'static str {
        let end_us = unix_us(Instant::now());
        let dropped = self.sub.dropped();
        let mut tail = Vec::new();
        for (i, (&received, &dropped)) in self.written.iter().zip(&dropped).enumerate() {
            tail.extend(pcapng::statistics(&pcapng::Statistics {
                interface: i as u32,
                start_us: self.start_us,
                end_us,
                received,
                dropped,
            }));
        }
        let total: u64 = dropped.iter().sum();
        let mut msg = Vec::new();
        message(&mut msg, DATA, &tail);
        let end = format!(
            "packets={} dropped={total} why={}",
            self.packets,
            why.replace(' ', "_")
        );
        message(&mut msg, END, end.as_bytes());
        let _ = write_within(wr, &msg).await;
        why
    }
}
