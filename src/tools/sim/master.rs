//! The simulated CIE-M10 as a master (`mbgate sim --role master`, docs/protocol.md §3):
//! every period it reads the slave's input port register (FC 03) and drives the
//! slave's output port register with its own inputs (FC 16), transaction ids counting
//! up from 0000, one query at a time; the inputs it reads become its outputs, shown on
//! the console. Its bytes go through the line model like the slave simulator's.

use super::line::Faults;
use super::options::Settings;
use super::packets::PacketDirection;
use super::role::Polling;
use super::serve::{ConsoleRequest, SimError, SimPort};
use super::{Device, Profile};
use crate::frame::framer::{Framed, Framer};
use crate::frame::hex::Hex;
use crate::frame::{Adu, ReplyJudge};
use crate::line::port::serial;
use crate::line::port::Backoff;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio::time::{sleep_until, Instant};
use tokio_serial::SerialStream;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

/// What the master waits for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Awaited {
    /// The next period.
    Idle,
    /// The reply to the read of the slave's inputs.
    Read,
    /// The reply to the write of the slave's outputs.
    Write,
}

/// The master's totals, logged when it stops.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct Totals {
    pub(crate) sent: u64,
    pub(crate) replies: u64,
    pub(crate) exceptions: u64,
    pub(crate) timeouts: u64,
}

struct SimulatedMaster {
    device: Device,
    polling: Polling,
    rx_faults: Faults,
    tx_faults: Faults,
    decoder: Framer,
    step: Awaited,
    tid: u16,
    /// The request awaiting its reply, and when the master gives up on it.
    asked: Option<(Adu, Instant)>,
    next_poll: Instant,
    /// The scheduled input change (`--toggle-ms`): the inputs count up.
    toggle: Option<tokio::time::Interval>,
    totals: Totals,
}

/// Runs the master until `shutdown` (or the console's `quit`).
pub(crate) async fn run(
    settings: Settings,
    polling: Polling,
    port: SimPort,
    mut commands: mpsc::Receiver<ConsoleRequest>,
    shutdown: CancellationToken,
) -> Result<Totals, SimError> {
    let mut m = SimulatedMaster {
        device: settings.device,
        polling,
        rx_faults: settings.rx_faults,
        tx_faults: settings.tx_faults,
        decoder: Framer::mbap(),
        step: Awaited::Idle,
        tid: 0,
        asked: None,
        next_poll: Instant::now(),
        toggle: settings.toggle.map(|period| {
            let mut i = tokio::time::interval_at(Instant::now() + period, period);
            i.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            i
        }),
        totals: Totals::default(),
    };
    let result = match port {
        SimPort::Stream(mut s) => m.serve(&mut s, &mut commands, &shutdown).await,
        SimPort::Listen(addr) => Err(std::io::Error::other(format!(
            "--role master sends on a serial port (--serial), not --listen {addr}"
        ))),
        SimPort::Path(cfg) => {
            let mut backoff = Backoff::new(Duration::from_millis(100), Duration::from_secs(2));
            loop {
                match serial::open(&cfg) {
                    Ok(mut s) => {
                        backoff.reset();
                        info!(serial = %cfg.path, "a CIE-M10 master on {}", cfg.path);
                        match m.serve(&mut s, &mut commands, &shutdown).await {
                            Ok(()) => break Ok(()),
                            Err(e) => warn!(serial = %cfg.path, "port lost ({e}); reopening"),
                        }
                    }
                    Err(e) => warn!(serial = %cfg.path, "cannot open the port ({e}); retrying"),
                }
                tokio::select! {
                    _ = shutdown.cancelled() => break Ok(()),
                    _ = tokio::time::sleep(backoff.next_delay()) => {}
                }
            }
        }
    };
    let t = m.totals;
    info!(
        sent = t.sent,
        replies = t.replies,
        exceptions = t.exceptions,
        timeouts = t.timeouts,
        "master stopped"
    );
    result.map(|()| t).map_err(SimError::Lost)
}

impl SimulatedMaster {
    fn cie(&mut self) -> &mut super::cie_m10::CieM10 {
        match &mut self.device.profile {
            Profile::CieM10(d) => d,
            Profile::Generic(_) | Profile::Replay(_) => {
                unreachable!("--role master is checked to be a cie-m10")
            }
        }
    }

    async fn serve(
        &mut self,
        port: &mut SerialStream,
        commands: &mut mpsc::Receiver<ConsoleRequest>,
        shutdown: &CancellationToken,
    ) -> std::io::Result<()> {
        let mut buf = vec![0u8; 1024];
        loop {
            let deadline = match self.asked.as_ref() {
                Some((_, d)) => *d,
                None => self.next_poll,
            };
            tokio::select! {
                _ = shutdown.cancelled() => return Ok(()),
                r = port.read(&mut buf) => match r {
                    Ok(0) => return Err(std::io::ErrorKind::UnexpectedEof.into()),
                    Ok(n) => {
                        let mut bytes = Vec::with_capacity(n);
                        self.rx_faults.apply(&buf[..n], &mut bytes);
                        self.decoder.push(&bytes);
                        while let Some(framed) = self.decoder.next_frame(&ReplyJudge, false) {
                            if let Framed::Frame(frame) = framed {
                                self.reply(frame);
                            }
                        }
                    }
                    Err(e) => return Err(e),
                },
                _ = sleep_until(deadline) => {
                    if let Some((req, _)) = self.asked.take() {
                        self.totals.timeouts += 1;
                        info!(target: "mbgate::tools::sim::packets", "no reply to {}", Hex(req.as_bytes()));
                        self.decoder.clear();
                        self.advance();
                    } else {
                        self.next_poll += self.polling.period;
                        self.next_poll = self.next_poll.max(Instant::now());
                        self.step = Awaited::Read;
                    }
                }
                Some(req) = commands.recv() => self.command(req),
                _ = async { self.toggle.as_mut().expect("guarded").tick().await }, if self.toggle.is_some() => {
                    let d = self.cie();
                    d.inputs = d.inputs.wrapping_add(1);
                }
            }
            if self.asked.is_none() && self.step != Awaited::Idle {
                self.ask(port).await?;
            }
        }
    }

    /// The next query of the period, or rest until the next period.
    fn advance(&mut self) {
        self.step = match self.step {
            Awaited::Read => Awaited::Write,
            Awaited::Write | Awaited::Idle => Awaited::Idle,
        };
    }

    /// Sends the query of the current step.
    async fn ask(&mut self, port: &mut SerialStream) -> std::io::Result<()> {
        let (unit, input, output, inputs) = {
            let d = self.cie();
            (d.unit, d.input_address, d.output_address, d.inputs)
        };
        let pdu = match self.step {
            Awaited::Read => {
                let [a, b] = input.to_be_bytes();
                vec![0x03, a, b, 0, 1]
            }
            Awaited::Write => {
                let [a, b] = output.to_be_bytes();
                vec![0x10, a, b, 0, 1, 2, 0, inputs]
            }
            Awaited::Idle => return Ok(()),
        };
        let adu = Adu::build(self.tid, unit, &pdu);
        self.tid = self.tid.wrapping_add(1);
        info!(target: "mbgate::tools::sim::packets", "tx {} (request)", Hex(adu.as_bytes()));
        self.device
            .log
            .record(PacketDirection::Tx, adu.as_bytes(), "request");
        let mut bytes = Vec::new();
        self.tx_faults.apply(adu.as_bytes(), &mut bytes);
        self.totals.sent += 1;
        self.asked = Some((adu, Instant::now() + self.polling.timeout));
        port.write_all(&bytes).await
    }

    /// A frame from the line: the reply to the query asked, or ignored.
    fn reply(&mut self, frame: Adu) {
        let answers = self.asked.as_ref().is_some_and(|(req, _)| {
            frame.tid() == req.tid()
                && frame.unit() == req.unit()
                && frame.function() & 0x7F == req.function()
        });
        if !answers {
            info!(target: "mbgate::tools::sim::packets", "rx {} (ignored: answers nothing asked)", Hex(frame.as_bytes()));
            self.device
                .log
                .record(PacketDirection::Rx, frame.as_bytes(), "ignored");
            return;
        }
        self.asked = None;
        self.totals.replies += 1;
        let pdu = frame.pdu();
        let note = if pdu[0] & 0x80 != 0 {
            self.totals.exceptions += 1;
            "exception"
        } else {
            "reply"
        };
        info!(target: "mbgate::tools::sim::packets", "rx {} ({note})", Hex(frame.as_bytes()));
        self.device
            .log
            .record(PacketDirection::Rx, frame.as_bytes(), note);
        if self.step == Awaited::Read && pdu.len() == 4 && pdu[..2] == [0x03, 2] {
            let read = pdu[3];
            let d = self.cie();
            if d.outputs != read {
                d.outputs = read;
                // The console shows what changed: the outputs follow the slave's inputs.
                println!("outputs {read:08b} (the slave's inputs)");
            }
        }
        self.advance();
    }

    fn command(&mut self, req: ConsoleRequest) {
        // The inputs set here go out with the next write; `quit` is the console's.
        let outcome = self.device.execute(req.command);
        let _ = req.reply.send(outcome.text);
    }
}
