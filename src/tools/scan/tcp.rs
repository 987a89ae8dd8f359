//! `mbgate scan --tcp`: a Modbus/TCP device or gateway, unit ids only, over one
//! connection (opened again if it closes). Exceptions 0x0A and 0x0B are a gateway
//! saying no device answers there, so they do not make a unit found; any other reply
//! does.

use super::probe::{self, Heard};
use super::{Found, Progress, Report, ScanError};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::{timeout_at, Instant};
use tokio_util::sync::CancellationToken;

/// A peer that closes this many connections in a row without replying is not asked
/// further.
const CLOSED_IN_A_ROW: usize = 3;

/// How long a connection may take.
const CONNECT: Duration = Duration::from_secs(5);

struct Conn {
    addr: String,
    stream: Option<TcpStream>,
    tid: u16,
    timeout: Duration,
    /// Connections the peer closed before replying, in a row.
    closed: usize,
}

impl Conn {
    async fn connect(&mut self) -> Result<&mut TcpStream, ScanError> {
        if self.stream.is_none() {
            let s = tokio::time::timeout(CONNECT, TcpStream::connect(&self.addr))
                .await
                .map_err(|_| {
                    std::io::Error::new(
                        std::io::ErrorKind::TimedOut,
                        format!("no connection to {} within {CONNECT:?}", self.addr),
                    )
                })?
                .map_err(|e| {
                    std::io::Error::new(e.kind(), format!("cannot connect to {}: {e}", self.addr))
                })?;
            let _ = s.set_nodelay(true);
            self.stream = Some(s);
        }
        Ok(self.stream.as_mut().expect("connected"))
    }

    /// Sends `pdu` to `unit`; the reply with its transaction id, or nothing within the
    /// timeout (a closed connection is opened again for the next).
    async fn ask(&mut self, unit: u8, pdu: &[u8]) -> Result<Heard, ScanError> {
        self.tid = self.tid.wrapping_add(1);
        let tid = self.tid;
        let mut frame = Vec::with_capacity(7 + pdu.len());
        frame.extend_from_slice(&tid.to_be_bytes());
        frame.extend_from_slice(&[0, 0]);
        frame.extend_from_slice(&(pdu.len() as u16 + 1).to_be_bytes());
        frame.push(unit);
        frame.extend_from_slice(pdu);
        let deadline = Instant::now() + self.timeout;
        let stream = self.connect().await?;
        if stream.write_all(&frame).await.is_err() {
            self.stream = None;
            self.closed += 1;
            return Ok(Heard::Nothing);
        }
        let mut got = Vec::new();
        let mut chunk = [0u8; 512];
        loop {
            while got.len() >= 7 {
                let len = usize::from(u16::from_be_bytes([got[4], got[5]]));
                if got.len() < 6 + len {
                    break;
                }
                let adu: Vec<u8> = got.drain(..6 + len).collect();
                if adu[..2] == tid.to_be_bytes() && len >= 2 {
                    self.closed = 0;
                    return Ok(Heard::Frame {
                        unit: adu[6],
                        pdu: adu[7..].to_vec(),
                    });
                }
            }
            match timeout_at(deadline, stream.read(&mut chunk)).await {
                Ok(Ok(n)) if n > 0 => got.extend_from_slice(&chunk[..n]),
                Ok(_) => {
                    self.stream = None;
                    self.closed += 1;
                    return Ok(Heard::Nothing);
                }
                Err(_) => return Ok(Heard::Nothing),
            }
        }
    }
}

/// Asks each of `units` at `addr`.
pub(super) async fn scan(
    addr: &str,
    units: &[u8],
    timeout: Duration,
    stop: &CancellationToken,
    progress: &mut Progress,
) -> Result<Report, ScanError> {
    let mut report = Report::default();
    let mut conn = Conn {
        addr: addr.to_string(),
        stream: None,
        tid: 0,
        timeout,
        closed: 0,
    };
    conn.connect().await?;
    for (i, &unit) in units.iter().enumerate() {
        if stop.is_cancelled() {
            break;
        }
        let left = timeout * (units.len() - i) as u32;
        progress.show(i, units.len(), left, &format!("{addr} unit {unit}"));
        let heard = conn.ask(unit, &probe::read_one(3)).await?;
        report.tries += 1;
        if conn.closed >= CLOSED_IN_A_ROW {
            // Each unit would only open and lose another connection.
            report.closed = Some(format!(
                "{addr} closed the connection without a reply {} times in a row \
                 (after unit {unit}): the scan stopped there",
                conn.closed
            ));
            break;
        }
        let Heard::Frame { pdu, .. } = heard else {
            continue;
        };
        // 0x0A, 0x0B: a gateway's word that nothing answers at this unit.
        if pdu.len() >= 2 && pdu[0] & 0x80 != 0 && matches!(pdu[1], 0x0A | 0x0B) {
            continue;
        }
        let mut f = Found {
            unit,
            serial: None,
            answered: probe::describe(&pdu),
            device_id: Err(probe::NoIdentity::NotAsked),
            server_id: Err(probe::NoIdentity::NotAsked),
            replies: Vec::new(),
            after: progress.started.elapsed(),
        };
        let device = conn.ask(unit, &probe::DEVICE_ID).await?;
        let server = conn.ask(unit, &probe::SERVER_ID).await?;
        report.tries += 2;
        super::identified(&mut f, &device, &server);
        report.found.push(f);
    }
    Ok(report)
}
