//! The master's transport: one request at a time to a gateway over TCP
//! (strict decoder, docs/design.md §1 step 1) or to a device on a serial port: MBAP
//! (the resynchronising decoder of docs/design.md §2, judging by transaction id and
//! shape), or RTU or ASCII (frames ended by their length, silence or line feed, and
//! checked by CRC or LRC; Modbus over Serial Line V1.02 §2.5.1, §2.5.2).

use crate::config::{Framing, RelayConfig, SerialConfig};
use crate::frame::framer::{Framed, Framer};
use crate::frame::mbap::{decode_strict, FrameRef};
use crate::frame::request::{self, decode_reply, Reply};
use crate::frame::serial::Expect;
use crate::frame::{pdu, Adu, FunctionCode, Judge, StrictError};
use bytes::BytesMut;
use std::io;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::{timeout_at, Instant};
use tokio_serial::SerialStream;

mod rtu_tcp;

/// The default TCP port of Modbus/TCP (docs/protocol.md §3).
const MODBUS_PORT: u16 = 502;

/// Why a request got no usable answer (exit code 1).
#[derive(Debug, thiserror::Error)]
pub(crate) enum ClientError {
    #[error("cannot connect to {addr}: {source}")]
    Connect { addr: String, source: io::Error },
    #[error("no connection to {addr} within {ms} ms")]
    ConnectTimeout { addr: String, ms: u64 },
    #[error("cannot open {path}: {source}")]
    Open {
        path: String,
        source: tokio_serial::Error,
    },
    #[error("no reply from {target} within {ms} ms")]
    Timeout { target: String, ms: u64 },
    #[error("{target}: {what}: {source}")]
    Io {
        target: String,
        what: &'static str,
        source: io::Error,
    },
    #[error("{target} closed the connection")]
    Closed { target: String },
    #[error("{target} sent a frame that is not Modbus/TCP: {source}")]
    Protocol { target: String, source: StrictError },
    #[error("{target} answered transaction {tid:#06x} with unit {unit}, not {asked}")]
    WrongUnit {
        target: String,
        tid: u16,
        unit: u8,
        asked: u8,
    },
    #[error("{target}: {source}")]
    Mismatch {
        target: String,
        source: request::Mismatch,
    },
}

/// The way to the device: a TCP connection (opened on first use, reopened after an
/// error) or a serial port (likewise).
#[derive(Debug)]
pub(crate) enum ClientTransport {
    Tcp {
        addr: String,
        stream: Option<TcpStream>,
        buf: BytesMut,
    },
    Serial {
        cfg: SerialConfig,
        port: Option<SerialStream>,
        /// Replies found by the port's framing: MBAP (the CIE-M10 serial Modbus/TCP
        /// mode, resynchronising), RTU or ASCII.
        decoder: Framer,
    },
    /// RTU (or ASCII) frames on a TCP connection: an `rtu` listener of a gateway, or
    /// a serial device server in raw TCP mode (`rtu_tcp.rs`).
    TcpFramed {
        addr: String,
        stream: Option<TcpStream>,
        decoder: Framer,
    },
}

impl ClientTransport {
    /// `HOST[:PORT]`; port 502 if left out.
    pub(crate) fn tcp(addr: &str) -> ClientTransport {
        let has_port = addr.parse::<std::net::SocketAddr>().is_ok()
            || addr.rsplit_once(':').is_some_and(|(host, port)| {
                !host.is_empty() && !host.ends_with(':') && port.parse::<u16>().is_ok()
            });
        let addr = if has_port {
            addr.to_string()
        } else if addr.contains(':') && !addr.starts_with('[') {
            format!("[{addr}]:{MODBUS_PORT}")
        } else {
            format!("{addr}:{MODBUS_PORT}")
        };
        ClientTransport::Tcp {
            addr,
            stream: None,
            buf: BytesMut::new(),
        }
    }

    /// `HOST[:PORT]` as [`ClientTransport::tcp`], its frames in `framing` (MBAP: [`ClientTransport::tcp`]).
    pub(crate) fn tcp_framed(addr: &str, framing: Framing) -> ClientTransport {
        let codec = match framing {
            Framing::Mbap => return ClientTransport::tcp(addr),
            Framing::Rtu => crate::frame::serial::Codec::Rtu,
            Framing::Ascii => crate::frame::serial::Codec::Ascii,
        };
        let ClientTransport::Tcp { addr, .. } = ClientTransport::tcp(addr) else {
            unreachable!("ClientTransport::tcp gives a Tcp transport")
        };
        ClientTransport::TcpFramed {
            addr,
            stream: None,
            decoder: Framer::serial(codec),
        }
    }

    pub(crate) fn serial(cfg: SerialConfig) -> ClientTransport {
        ClientTransport::Serial {
            decoder: cfg.framing.framer(),
            cfg,
            port: None,
        }
    }

    /// The bytes `adu` is on this transport's wire: MBAP as it is, RTU or ASCII as the
    /// unit and PDU in that framing, check included.
    pub(crate) fn wire(&self, adu: &Adu) -> Vec<u8> {
        match self {
            ClientTransport::Serial { decoder, .. }
            | ClientTransport::TcpFramed { decoder, .. } => decoder.encode(adu),
            ClientTransport::Tcp { .. } => adu.as_bytes().to_vec(),
        }
    }

    /// What error messages call it: the address or the port's path.
    pub(crate) fn name(&self) -> &str {
        match self {
            ClientTransport::Tcp { addr, .. } | ClientTransport::TcpFramed { addr, .. } => addr,
            ClientTransport::Serial { cfg, .. } => &cfg.path,
        }
    }

    /// Forgets the connection or port; the next request opens it again.
    fn close(&mut self) {
        match self {
            ClientTransport::Tcp { stream, buf, .. } => {
                *stream = None;
                buf.clear();
            }
            ClientTransport::Serial { port, decoder, .. } => {
                *port = None;
                decoder.clear();
            }
            ClientTransport::TcpFramed {
                stream, decoder, ..
            } => {
                *stream = None;
                decoder.clear();
            }
        }
    }
}

/// Accepts only the answer to one request (docs/design.md §1 step 4): its transaction id,
/// its unit id, its function code (or exception) and the shape it calls for.
struct ReplyTo<'a>(&'a Adu);

impl Judge for ReplyTo<'_> {
    fn plausible_function(&self, code: FunctionCode) -> bool {
        code.is_reply() || code.base() == self.0.function_code()
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        frame.tid() == self.0.tid()
            && frame.unit() == self.0.unit()
            && pdu::reply_matches(self.0.pdu(), frame.pdu())
    }

    fn expect(&self) -> Expect<'_> {
        Expect::Reply(self.0.pdu())
    }
}

/// One answered request.
#[derive(Debug, Clone)]
pub(crate) struct Exchange {
    /// The reply frame.
    pub(crate) reply: Adu,
    /// What it says.
    pub(crate) decoded: Reply,
    /// From the first byte written to the reply decoded.
    pub(crate) round_trip: Duration,
    /// TCP: whole frames that answered something else (another transaction id).
    pub(crate) ignored: Vec<Adu>,
    /// Serial: bytes the resynchronising decoder dropped while waiting.
    pub(crate) dropped_bytes: u64,
}

/// What a transport hands back before decoding.
struct TransportReply {
    reply: Adu,
    round_trip: Duration,
    ignored: Vec<Adu>,
    dropped_bytes: u64,
}

/// A Modbus master on one transport: numbers the requests (transaction ids 1, 2, ...,
/// never 0x0000, which the device's own change notifications may use: docs/design.md §1
/// step 3) and waits for each answer, bounded by the timeout.
#[derive(Debug)]
pub(crate) struct Master {
    transport: ClientTransport,
    timeout: Duration,
    next_tid: u16,
}

impl Master {
    pub(crate) fn new(transport: ClientTransport, timeout: Duration) -> Master {
        Master {
            transport,
            timeout,
            next_tid: 1,
        }
    }

    pub(crate) fn transport(&self) -> &ClientTransport {
        &self.transport
    }

    /// The transaction id for the next request; each call gives a new one.
    pub(crate) fn next_tid(&mut self) -> u16 {
        let tid = self.next_tid;
        self.next_tid = self.next_tid.checked_add(1).unwrap_or(1);
        tid
    }

    /// Sends `request` and waits, at most the timeout in all (connecting or opening
    /// included), for its answer. After an I/O or protocol error the transport is closed,
    /// to be reopened by the next request; after a timeout it is kept (a late answer
    /// is recognised by its transaction id and ignored).
    pub(crate) async fn transact(&mut self, request: &Adu) -> Result<Exchange, ClientError> {
        let deadline = Instant::now() + self.timeout;
        let ms = self.timeout.as_millis() as u64;
        let received = match &mut self.transport {
            ClientTransport::Tcp { addr, stream, buf } => {
                tcp_exchange(addr, stream, buf, request, deadline, ms).await
            }
            ClientTransport::Serial { cfg, port, decoder } => {
                serial_exchange(cfg, port, decoder, request, deadline, ms).await
            }
            ClientTransport::TcpFramed {
                addr,
                stream,
                decoder,
            } => rtu_tcp::exchange(addr, stream, decoder, request, deadline, ms).await,
        };
        // Over TCP a frame with our transaction id may still answer something else;
        // on an MBAP serial line the judge has already checked (docs/design.md §1
        // step 4); an RTU or ASCII reply whose check held is judged here.
        let result = received.and_then(|r| match decode_reply(request.pdu(), r.reply.pdu()) {
            Ok(decoded) => Ok(Exchange {
                reply: r.reply,
                decoded,
                round_trip: r.round_trip,
                ignored: r.ignored,
                dropped_bytes: r.dropped_bytes,
            }),
            Err(source) => Err(ClientError::Mismatch {
                target: self.transport.name().to_string(),
                source,
            }),
        });
        if matches!(
            result,
            Err(ClientError::Io { .. }
                | ClientError::Closed { .. }
                | ClientError::Protocol { .. }
                | ClientError::WrongUnit { .. }
                | ClientError::Mismatch { .. })
        ) {
            self.transport.close();
        }
        result
    }
}

/// The connection to `addr`, made now (before `deadline`) when there is none, with
/// `fresh` run on a new one (what was buffered from an old one answers nothing).
async fn connected<'a>(
    addr: &str,
    stream: &'a mut Option<TcpStream>,
    deadline: Instant,
    ms: u64,
    fresh: impl FnOnce(),
) -> Result<&'a mut TcpStream, ClientError> {
    if stream.is_none() {
        let s = match timeout_at(deadline, TcpStream::connect(addr)).await {
            Err(_) => {
                let addr = addr.to_string();
                return Err(ClientError::ConnectTimeout { addr, ms });
            }
            Ok(Err(source)) => {
                let addr = addr.to_string();
                return Err(ClientError::Connect { addr, source });
            }
            Ok(Ok(s)) => s,
        };
        let _ = s.set_nodelay(true);
        fresh();
        *stream = Some(s);
    }
    Ok(stream.as_mut().expect("connected above"))
}

async fn tcp_exchange(
    addr: &str,
    stream: &mut Option<TcpStream>,
    buf: &mut BytesMut,
    request: &Adu,
    deadline: Instant,
    ms: u64,
) -> Result<TransportReply, ClientError> {
    let target = || addr.to_string();
    let s = connected(addr, stream, deadline, ms, || buf.clear()).await?;
    let start = Instant::now();
    let io = |what, source| ClientError::Io {
        target: target(),
        what,
        source,
    };
    let mut ignored = Vec::new();
    let wait = async {
        s.write_all(request.as_bytes())
            .await
            .map_err(|e| io("sending", e))?;
        loop {
            while let Some(frame) = decode_strict(buf).map_err(|source| ClientError::Protocol {
                target: target(),
                source,
            })? {
                if frame.tid() != request.tid() {
                    ignored.push(frame);
                    continue;
                }
                if frame.unit() != request.unit() {
                    return Err(ClientError::WrongUnit {
                        target: target(),
                        tid: frame.tid(),
                        unit: frame.unit(),
                        asked: request.unit(),
                    });
                }
                return Ok(frame);
            }
            if s.read_buf(buf).await.map_err(|e| io("receiving", e))? == 0 {
                return Err(ClientError::Closed { target: target() });
            }
        }
    };
    let result = timeout_at(deadline, wait).await;
    received(result, target, ms, start, ignored, 0)
}

/// One request on a serial port, in the port's framing, and the first frame that
/// answers it.
///
/// - MBAP: the resynchronising framer with [`ReplyTo`] as its judge; a partial
///   candidate is discarded after the frame gap. Bytes kept from an earlier exchange
///   may hold a late answer, recognised by its transaction id.
/// - RTU or ASCII: the first frame whose CRC or LRC holds and that comes from the unit
///   asked, ended by its length or a silence of 3.5 character times (RTU, never
///   shorter than `silence_floor_ms`) or its line feed (ASCII). Whatever came before
///   the request answers nothing. Frames from another unit and bytes that make no
///   good frame are skipped and counted.
async fn serial_exchange(
    cfg: &SerialConfig,
    port: &mut Option<SerialStream>,
    decoder: &mut Framer,
    request: &Adu,
    deadline: Instant,
    ms: u64,
) -> Result<TransportReply, ClientError> {
    let target = || cfg.path.clone();
    let fresh = port.is_none();
    let p = open_port(cfg, port)?;
    if fresh {
        decoder.clear();
    }
    let judge = ReplyTo(request);
    let dropped_before = decoder.dropped();
    let mut skipped = 0u64;
    let start = Instant::now();
    let io = |what, source| ClientError::Io {
        target: target(),
        what,
        source,
    };
    let silence = silence(cfg, decoder);
    let wait = async {
        if decoder.codec().is_some() {
            // Whatever came before the request answers nothing.
            decoder.clear();
        }
        p.write_all(&decoder.encode(request))
            .await
            .map_err(|e| io("sending", e))?;
        let mut chunk = [0u8; 512];
        let mut last_byte = Instant::now();
        let mut quiet = false;
        loop {
            if let Some(reply) = answer_in(decoder, &judge, request, quiet, &mut skipped) {
                return Ok(reply);
            }
            let quiet_at = (decoder.buffered() > 0 && decoder.silence_ends_frames())
                .then(|| last_byte + silence);
            match read_until(p, &mut chunk, quiet_at).await {
                None => quiet = true,
                Some(read) => {
                    let n = received_bytes(read, &io, target)?;
                    decoder.push(&chunk[..n]);
                    last_byte = Instant::now();
                    quiet = false;
                }
            }
        }
    };
    let result = timeout_at(deadline, wait).await;
    let dropped_bytes = decoder.dropped() - dropped_before + skipped;
    received(result, target, ms, start, Vec::new(), dropped_bytes)
}

/// Silence after which a partial frame is discarded: on MBAP the gateway's default
/// `relay.frame_gap_ms` (docs/design.md §2), on RTU 3.5 character times.
fn silence(cfg: &SerialConfig, decoder: &Framer) -> Duration {
    match decoder.codec() {
        None => Duration::from_millis(RelayConfig::default().frame_gap_ms),
        Some(_) => {
            let port = crate::line::port::kind::PortInfo::plain(
                crate::line::port::serial::of_path(&cfg.path),
            );
            crate::line::port::kind::silence(cfg, &port)
        }
    }
}

/// The answer to `request` among the frames `decoder` holds (`quiet`: the line has
/// paused); frames from another unit counted in `skipped`.
fn answer_in(
    decoder: &mut Framer,
    judge: &ReplyTo,
    request: &Adu,
    quiet: bool,
    skipped: &mut u64,
) -> Option<Adu> {
    while let Some(framed) = decoder.next_frame(judge, quiet) {
        match framed {
            // MBAP: the judge took only the answer; RTU/ASCII: from the unit.
            Framed::Frame(frame) if frame.unit() == request.unit() => {
                return Some(frame.with_tid(request.tid()));
            }
            Framed::Frame(frame) => {
                *skipped += decoder.encoded_len(frame.pdu().len()) as u64;
            }
            Framed::Corrupt(_) => {}
        }
    }
    None
}

/// Opens the serial port if it is not open.
fn open_port<'a>(
    cfg: &SerialConfig,
    port: &'a mut Option<SerialStream>,
) -> Result<&'a mut SerialStream, ClientError> {
    if port.is_none() {
        let p = crate::line::port::serial::open(cfg).map_err(|source| ClientError::Open {
            path: cfg.path.clone(),
            source,
        })?;
        *port = Some(p);
    }
    Ok(port.as_mut().expect("opened above"))
}

/// The next read from the port, or `None` once `quiet_at` (if any) passes first: a
/// partial frame then ends at silence.
async fn read_until(
    p: &mut SerialStream,
    chunk: &mut [u8],
    quiet_at: Option<Instant>,
) -> Option<std::io::Result<usize>> {
    match quiet_at {
        Some(at) => timeout_at(at, p.read(chunk)).await.ok(),
        None => Some(p.read(chunk).await),
    }
}

/// How many bytes a read brought; the port closing or failing is the exchange's end.
fn received_bytes(
    read: std::io::Result<usize>,
    io: &impl Fn(&'static str, std::io::Error) -> ClientError,
    target: impl Fn() -> String,
) -> Result<usize, ClientError> {
    match read.map_err(|e| io("receiving", e))? {
        0 => Err(ClientError::Closed { target: target() }),
        n => Ok(n),
    }
}

/// The exchange's outcome: the reply with what was seen on the way, or a timeout.
fn received(
    result: Result<Result<Adu, ClientError>, tokio::time::error::Elapsed>,
    target: impl Fn() -> String,
    ms: u64,
    start: Instant,
    ignored: Vec<Adu>,
    dropped_bytes: u64,
) -> Result<TransportReply, ClientError> {
    match result {
        Err(_) => Err(ClientError::Timeout {
            target: target(),
            ms,
        }),
        Ok(result) => result.map(|reply| TransportReply {
            reply,
            round_trip: start.elapsed(),
            ignored,
            dropped_bytes,
        }),
    }
}

#[cfg(test)]
mod tests;
