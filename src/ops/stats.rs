//! Counters the gateway keeps (docs/design.md §1: dropped and late frames are counted).

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};

macro_rules! counters {
    ($($name:ident: $doc:literal),* $(,)?) => {
        /// Running totals since start, each only ever added to (there is no `set`: two
        /// writers of one counter cannot overwrite each other's counts). Written by
        /// their owning task, read by anyone.
        #[derive(Debug, Default)]
        pub struct Stats {
            $(#[doc = $doc] pub $name: AtomicU64,)*
        }

        impl Stats {
            /// The sum of `parts`, counter by counter: the gateway's totals from its
            /// listeners' counters and each line's own.
            pub(crate) fn total<'a>(parts: impl IntoIterator<Item = &'a Stats>) -> Stats {
                let sum = Stats::default();
                for p in parts {
                    $(sum.$name.fetch_add(p.$name.load(Ordering::Relaxed), Ordering::Relaxed);)*
                }
                sum
            }
        }

        impl fmt::Display for Stats {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                let mut first = true;
                $(
                    if !first { f.write_str(" ")?; }
                    first = false;
                    write!(f, "{}={}", stringify!($name), self.$name.load(Ordering::Relaxed))?;
                )*
                let _ = first;
                Ok(())
            }
        }
    };
}

counters! {
    connections: "TCP connections accepted.",
    connections_refused: "TCP connections closed at once: `max_connections` reached.",
    connections_closed: "TCP connections accepted and since closed.",
    connections_denied: "TCP connections closed at once, before any byte was read: the source address is not in the listener's `allow` list.",
    tls_failed: "TLS connections closed before the handshake ended: it failed (no client certificate, another CA, expired, an old protocol) or took longer than `handshake_timeout_ms`.",
    tls_refused: "TLS masters closed after the handshake: their certificate carried no role (and the listener has no `default_role`), a role no `[[role]]` names, or a malformed role.",
    denied: "Requests answered 0x01 without reaching the line: the listener's or the master's role's access rules do not permit them.",
    protocol_violations: "Connections closed for a frame that failed the strict MBAP checks.",
    dial_answers: "Answers of a dialed server to mbgate's identity or heartbeat (their echoes, or bytes that are no request, one answer each at most): dropped, never relayed (docs/dialing.md).",
    datagrams_dropped: "UDP datagrams dropped: not exactly one MBAP request, or beyond their source's share.",
    not_requests: "Frames from masters that are no request but an answer (an exception, a reply's shape, or on UDP the gateway's own reply sent back): dropped, never answered (docs/security.md \"Threat model\").",
    exceptions_limited: "Exception replies not sent to a UDP source past its budget of them (docs/dialing.md \"Modbus over UDP\").",
    requests: "Requests handed to the relay.",
    replies: "Device replies delivered to masters (one reply to reads joined together counts once for each master).",
    coalesced: "Reads that joined an identical read waiting for the line (`coalesce`): answered by its transaction.",
    served_from_cache: "Reads answered from the reply to an identical read younger than `cache_ms`.",
    timeouts: "Requests answered 0x0B: no reply in time, or the port was lost under them.",
    unavailable: "Requests answered 0x0A: no serial port, or shutting down.",
    busy: "Requests answered 0x06: the queue was full.",
    bad_requests: "Requests answered locally because their PDU broke protocol limits.",
    retries: "Requests resent after a timeout.",
    late_replies: "Replies to a request no longer outstanding (timed out, or answered already): dropped.",
    notifications_dropped: "Frames answering no request, dropped (`notifications = drop`).",
    notifications_broadcast: "Frames answering no request, broadcast to every master.",
    notifications_missed: "Broadcasts a master missed because it was not reading.",
    dropped_bytes: "Serial bytes discarded, for any reason (those below among them).",
    dropped_too_early: "Of dropped_bytes: read before their request could have left the wire at baud_rate (RTU/ASCII; a wire only: docs/reliability.md \"Knowing the wire\").",
    dropped_echo: "Of dropped_bytes: MBAP copies of a request that began before it could have left the wire at baud_rate: its echo (a wire only).",
    dropped_stale: "Of dropped_bytes: there before their request was sent (a late reply, a frame begun earlier), or answering no request.",
    unasked_bytes: "MBAP: bytes from the device while nothing was asked and no late reply could come.",
    withdrawn_bytes: "RTU/ASCII: bytes of a request that timed out still in the port's output queue (flow control held them, or the adapter stopped sending), withdrawn (TCOFLUSH): the device never gets a request its master was told failed (docs/reliability.md \"RTU and ASCII\").",
    refuted_frames: "Replies that what followed them showed to have lost bytes: dropped.",
    bad_frames: "RTU/ASCII replies whose CRC or LRC failed, or that came from another unit than the one asked; MBAP replies with a request's id and unit that did not fit it.",
    backed_off: "Requests answered 0x0B at once: their unit was backed off (RTU/ASCII).",
    broadcasts: "Broadcasts (unit 0) sent on an RTU/ASCII line.",
    broadcasts_refused: "Requests to unit 0 on an RTU/ASCII line that a broadcast cannot carry (a read, or any function but a write): answered 0x01, never sent.",
    serial_bytes_in: "Bytes read from the serial port.",
    serial_bytes_out: "Bytes written to the serial port.",
    serial_opens: "Times the serial port was opened.",
}

impl Stats {
    pub(crate) fn add(&self, counter: &AtomicU64, n: u64) {
        counter.fetch_add(n, Ordering::Relaxed);
    }

    /// The current value of one of this struct's counters (`stats.get(&stats.requests)`).
    pub fn get(&self, counter: &AtomicU64) -> u64 {
        counter.load(Ordering::Relaxed)
    }
}
