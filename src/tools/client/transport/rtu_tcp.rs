//! One request as RTU (or ASCII) frames on a TCP connection: to a gateway's `rtu`
//! listener or a serial device server in raw TCP mode. The frame is sent with its CRC
//! and no MBAP header; the reply is the first frame from the unit asked whose check
//! holds, ended by its length (or, for a reply of unknown shape, a pause).

use super::{connected, received, ClientError, TransportReply};
use crate::frame::framer::{Framed, Framer, ReplyFor};
use crate::frame::Adu;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::{timeout_at, Instant};

/// A pause this long ends a reply of unknown shape: the far end writes a reply in one
/// go, so its bytes are never this far apart on a socket.
const SILENCE: Duration = Duration::from_millis(50);

pub(super) async fn exchange(
    addr: &str,
    stream: &mut Option<TcpStream>,
    decoder: &mut Framer,
    request: &Adu,
    deadline: Instant,
    ms: u64,
) -> Result<TransportReply, ClientError> {
    let target = || addr.to_string();
    let s = connected(addr, stream, deadline, ms, || {
        decoder.clear();
    })
    .await?;
    let start = Instant::now();
    let io = |what, source| ClientError::Io {
        target: target(),
        what,
        source,
    };
    let mut dropped_bytes = 0u64;
    let wait = async {
        // Whatever came before the request answers nothing (a late reply).
        dropped_bytes += decoder.clear() as u64;
        let frame = decoder.encode(request);
        s.write_all(&frame).await.map_err(|e| io("sending", e))?;
        let mut chunk = [0u8; 512];
        let mut quiet = false;
        loop {
            if let Some(reply) = reply_in(decoder, request, quiet, &mut dropped_bytes) {
                return Ok(reply);
            }
            let pause = decoder.buffered() > 0 && decoder.silence_ends_frames();
            let read = if pause {
                match tokio::time::timeout(SILENCE, s.read(&mut chunk)).await {
                    Ok(read) => read,
                    Err(_) => {
                        quiet = true;
                        continue;
                    }
                }
            } else {
                s.read(&mut chunk).await
            };
            match read.map_err(|e| io("receiving", e))? {
                0 => return Err(ClientError::Closed { target: target() }),
                n => {
                    decoder.push(&chunk[..n]);
                    quiet = false;
                }
            }
        }
    };
    let result = timeout_at(deadline, wait).await;
    received(result, target, ms, start, Vec::new(), dropped_bytes)
}

/// The reply to `request` among the frames `decoder` holds (`quiet`: the line has
/// paused), the others counted in `dropped_bytes`.
fn reply_in(
    decoder: &mut Framer,
    request: &Adu,
    quiet: bool,
    dropped_bytes: &mut u64,
) -> Option<Adu> {
    while let Some(framed) = decoder.next_frame(&ReplyFor(request.pdu()), quiet) {
        match framed {
            Framed::Frame(reply) if reply.unit() == request.unit() => {
                return Some(reply.with_tid(request.tid()));
            }
            Framed::Frame(other) => {
                *dropped_bytes += decoder.encoded_len(other.pdu().len()) as u64;
            }
            Framed::Corrupt(n) => *dropped_bytes += n as u64,
        }
    }
    None
}
