//! What the relay says about its line (docs/watching.md), in process: the relay
//! over an in-memory pipe (src/line/port/duplex.rs) with a device written here, its log
//! captured. A unit that stops answering is warned about once and its return said
//! once, on MBAP and on RTU (and when its answers were being dropped, why, naming the
//! setting); the cost of MBAP confirmation is said once; the traffic log shows whole
//! frames with both transaction ids.

use mbgate::config::{Framing, RelayConfig, SerialConfig};
use mbgate::frame::serial::Codec;
use mbgate::frame::Adu;
use mbgate::line::outbox::{Inbox, Outbox};
use mbgate::line::port::duplex;
use mbgate::line::relay::{Command, Relay, RelayHandle};
use mbgate::ops::stats::Stats;
use std::io::Write;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};
use tokio::time::timeout;
use tokio_util::sync::CancellationToken;

const MS: Duration = Duration::from_millis(1);
const SEC: Duration = Duration::from_secs(1);

/// Everything logged while it is in scope, as text (no colours).
#[derive(Clone, Default)]
struct Log(Arc<Mutex<Vec<u8>>>);

impl Write for Log {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Log {
    fn capture() -> (Self, tracing::subscriber::DefaultGuard) {
        let log = Log::default();
        let writer = log.clone();
        let sub = tracing_subscriber::fmt()
            .with_max_level(tracing::Level::DEBUG)
            .with_ansi(false)
            .with_writer(move || writer.clone())
            .finish();
        (log, tracing::subscriber::set_default(sub))
    }

    fn text(&self) -> String {
        String::from_utf8_lossy(&self.0.lock().unwrap()).into_owned()
    }

    /// The lines at `level` that contain `what`.
    fn lines(&self, level: &str, what: &str) -> Vec<String> {
        let text = self.text();
        let lines = text
            .lines()
            .filter(|l| l.contains(level) && l.contains(what));
        lines.map(str::to_owned).collect()
    }
}

struct Gw {
    handle: RelayHandle,
    shutdown: CancellationToken,
    task: tokio::task::JoinHandle<()>,
    dev: DuplexStream,
    outbox: Outbox,
    inbox: Inbox,
}

async fn start(framing: Framing, cfg: RelayConfig, traffic: bool) -> Gw {
    let serial = SerialConfig {
        path: "unused".into(),
        baud_rate: 115_200,
        framing,
        silence_floor_ms: mbgate::config::Floor::Ms(5),
        ..SerialConfig::default()
    };
    start_on(serial, cfg, traffic).await
}

/// [`start`] with these serial settings.
async fn start_on(serial: SerialConfig, cfg: RelayConfig, traffic: bool) -> Gw {
    let shutdown = CancellationToken::new();
    let (port, mut device) = duplex::pair(4096, Duration::from_nanos(86_806));
    let stats = Arc::new(Stats::default());
    let (relay, handle) = Relay::new(cfg, serial, traffic, stats, shutdown.clone());
    let task = tokio::spawn(relay.with_port(Box::new(port)).run());
    let dev = device.accept().await;
    let (outbox, inbox) = Outbox::new(16);
    let notifier = outbox.notifier();
    handle.send(Command::Attach { conn: 7, notifier }).unwrap();
    Gw {
        handle,
        shutdown,
        task,
        dev,
        outbox,
        inbox,
    }
}

impl Gw {
    async fn ask(&mut self, adu: Adu) -> Adu {
        let ticket = self.outbox.ticket().await;
        let cmd = Command::Request {
            conn: 7,
            adu,
            ticket,
        };
        self.handle.send(cmd).unwrap();
        let out = timeout(3 * SEC, self.inbox.next()).await.expect("in time");
        out.expect("open").adu()
    }

    async fn stop(self) {
        self.shutdown.cancel();
        timeout(3 * SEC, self.task).await.expect("drained").unwrap();
    }
}

fn read(tid: u16, unit: u8) -> Adu {
    Adu::build(tid, unit, &[0x03, 0x00, 0x0A, 0x00, 0x02])
}

fn exception_of(reply: &Adu) -> Option<u8> {
    (reply.function() & 0x80 != 0).then(|| reply.pdu()[1])
}

/// The MBAP device: takes one request and, if `answer`, replies to it.
async fn mbap_device(dev: &mut DuplexStream, answer: bool) {
    let mut head = [0u8; 6];
    timeout(3 * SEC, dev.read_exact(&mut head))
        .await
        .unwrap()
        .unwrap();
    let mut rest = vec![0u8; usize::from(u16::from_be_bytes([head[4], head[5]]))];
    dev.read_exact(&mut rest).await.unwrap();
    if answer {
        let tid = u16::from_be_bytes([head[0], head[1]]);
        let reply = Adu::build(tid, rest[0], &[0x03, 0x04, 0, 1, 0, 2]);
        dev.write_all(reply.as_bytes()).await.unwrap();
    }
}

#[tokio::test]
async fn mbap_a_unit_that_stops_answering_is_warned_about_once_and_its_return_said_once() {
    let (log, _guard) = Log::capture();
    let cfg = RelayConfig {
        response_timeout_ms: 60,
        ..RelayConfig::default()
    };
    let mut gw = start(Framing::Mbap, cfg, false).await;
    let mut dev = std::mem::replace(&mut gw.dev, tokio::io::duplex(1).0);
    // Answered, then six timeouts, then answered again, then three more timeouts and
    // an answer within the minute: a second spell, not warned about.
    let plan = [true, false, false, false, false, false, false, true]
        .into_iter()
        .chain([false, false, false, true]);
    let device = tokio::spawn(async move {
        for answer in plan {
            mbap_device(&mut dev, answer).await;
        }
        dev
    });
    let mut got = Vec::new();
    for tid in 0..12 {
        got.push(exception_of(&gw.ask(read(tid, 1)).await));
    }
    let n = None;
    let t = Some(0x0B);
    assert_eq!(got, [n, t, t, t, t, t, t, n, t, t, t, n]);
    gw.dev = device.await.unwrap();
    let warned = log.lines("WARN", "not answering");
    assert_eq!(warned.len(), 1, "{}", log.text());
    assert!(
        warned[0].contains("unit 1 on duplex not answering: 3 timeouts in 0."),
        "{}",
        warned[0]
    );
    let back = log.lines("INFO", "answering again");
    assert_eq!(back.len(), 1, "{}", log.text());
    assert!(
        back[0].contains("unit 1 on duplex answering again, after 6 timeouts in "),
        "{}",
        back[0]
    );
    // Nothing else at warning level.
    assert_eq!(log.lines("WARN", "").len(), 1, "{}", log.text());
    gw.stop().await;
}

#[tokio::test]
async fn rtu_a_backed_off_unit_is_warned_about_once_and_its_return_said_once() {
    let (log, _guard) = Log::capture();
    let cfg = RelayConfig {
        response_timeout_ms: 40,
        unit_backoff_ms: 150,
        unit_backoff_max_ms: 300,
        probe_timeout_ms: 40,
        timeout_guard_ms: 5,
        ..RelayConfig::default()
    };
    let mut gw = start(Framing::Rtu, cfg, true).await;
    let mut dev = std::mem::replace(&mut gw.dev, tokio::io::duplex(1).0);
    let request = Codec::Rtu.encode(2, &[0x03, 0x00, 0x0A, 0x00, 0x02]);
    let reply = Codec::Rtu.encode(2, &[0x03, 0x04, 0, 1, 0, 2]);
    let reply_hex = mbgate::frame::hex::Hex(&reply).to_string();
    // Three timeouts back the unit off; two probes fail (each a timeout), the third
    // is answered.
    let device = tokio::spawn(async move {
        for answer in [false, false, false, false, false, true] {
            let mut b = vec![0u8; request.len()];
            timeout(3 * SEC, dev.read_exact(&mut b))
                .await
                .unwrap()
                .unwrap();
            assert_eq!(b, request);
            if answer {
                tokio::time::sleep(2 * MS).await;
                dev.write_all(&reply).await.unwrap();
            }
        }
        dev
    });
    let mut answers = 0;
    for tid in 0..200 {
        let got = gw.ask(read(tid, 2)).await;
        if exception_of(&got).is_none() {
            answers += 1;
            break;
        }
        tokio::time::sleep(10 * MS).await;
    }
    assert_eq!(answers, 1, "{}", log.text());
    gw.dev = device.await.unwrap();
    let warned = log.lines("WARN", "");
    assert_eq!(warned.len(), 1, "{}", log.text());
    assert!(
        warned[0].contains("unit 2 on duplex not answering: 3 timeouts in"),
        "{}",
        warned[0]
    );
    let back = log.lines("INFO", "answering again");
    assert_eq!(back.len(), 1, "{}", log.text());
    assert!(
        back[0].contains("unit 2 on duplex answering again, after 5 timeouts in"),
        "{}",
        back[0]
    );
    // The reply in the traffic log as it was on the wire, CRC and all.
    let wire = log.lines("DEBUG", "serial->gw");
    assert_eq!(wire.len(), 1, "{}", log.text());
    assert!(
        wire[0].contains(&format!("{reply_hex} dir=\"serial->gw\" conn=7 unit=2")),
        "{}",
        wire[0]
    );
    gw.stop().await;
}

#[tokio::test]
async fn mbap_the_cost_of_confirmation_is_said_once_and_the_traffic_log_shows_whole_frames() {
    let (log, _guard) = Log::capture();
    // A device said to send notifications: every reply waits for the pause.
    let relay = RelayConfig {
        device_notifications: true,
        ..RelayConfig::default()
    };
    let mut gw = start(Framing::Mbap, relay, true).await;
    let mut dev = std::mem::replace(&mut gw.dev, tokio::io::duplex(1).0);
    let device = tokio::spawn(async move {
        for _ in 0..3 {
            mbap_device(&mut dev, true).await;
        }
        dev
    });
    for tid in [0x0101, 0x0202, 0x0303] {
        let got = gw.ask(read(tid, 1)).await;
        assert_eq!(got.tid(), tid);
        assert_eq!(got.pdu(), [0x03, 0x04, 0, 1, 0, 2]);
    }
    gw.dev = device.await.unwrap();
    let told = log.lines("INFO", "quiet for 5.00 ms after it");
    assert_eq!(told.len(), 1, "{}", log.text());
    assert!(told[0].contains("serial.silence_floor_ms"), "{}", told[0]);
    // Each request and reply as one line: direction, master, unit, both ids, function,
    // address and count, the whole frame.
    let out = log.lines("DEBUG", "gw->serial");
    assert_eq!(out.len(), 3, "{}", log.text());
    assert!(
        out[1].contains("conn=7 unit=1 tid=514 line_tid=")
            && out[1].contains("fc=3 addr=10 count=2")
            && out[1].contains("00 00 00 06 01 03 00 0A 00 02"),
        "{}",
        out[1]
    );
    let back = log.lines("DEBUG", "serial->gw");
    assert_eq!(back.len(), 3, "{}", log.text());
    assert!(
        back[2].contains("conn=7 unit=1 tid=771 line_tid=")
            && back[2].contains("fc=3 addr=10 count=2")
            && back[2].contains("00 07 01 03 04 00 01 00 02"),
        "{}",
        back[2]
    );
    gw.stop().await;
}

/// A loopback on a port declared a wire at 9600 baud (`port_kind = "wire"`): each FC 06
/// write comes straight back, byte for byte its reply, before it could have left the
/// wire, and is dropped as its echo. The warning says the answers were dropped as
/// echoes, how many bytes, and names the settings, not "not answering".
#[tokio::test]
async fn answers_dropped_as_echoes_are_said_in_the_warning() {
    let (log, _guard) = Log::capture();
    let serial = SerialConfig {
        path: "unused".into(),
        baud_rate: 9600,
        port_kind: mbgate::config::PortKind::Wire,
        ..SerialConfig::default()
    };
    let cfg = RelayConfig {
        response_timeout_ms: 60,
        ..RelayConfig::default()
    };
    let mut gw = start_on(serial, cfg, false).await;
    let mut dev = std::mem::replace(&mut gw.dev, tokio::io::duplex(1).0);
    let device = tokio::spawn(async move {
        for _ in 0..3 {
            let mut req = [0u8; 12];
            timeout(3 * SEC, dev.read_exact(&mut req))
                .await
                .unwrap()
                .unwrap();
            dev.write_all(&req).await.unwrap();
        }
        dev
    });
    for tid in 0..3 {
        let write = Adu::build(tid, 1, &[0x06, 0, 8, 0, 0x11]);
        assert_eq!(exception_of(&gw.ask(write).await), Some(0x0B));
    }
    gw.dev = device.await.unwrap();
    let warned = log.lines("WARN", "unit 1 on duplex");
    assert_eq!(warned.len(), 1, "{}", log.text());
    assert!(
        warned[0].contains("3 timeouts in")
            && warned[0].contains("dropped as echoes: 36 bytes")
            && warned[0].contains("serial.baud_rate = 9600")
            && warned[0].contains("serial.port_kind"),
        "{}",
        warned[0]
    );
    assert!(!warned[0].contains("not answering"), "{}", warned[0]);
    gw.stop().await;
}
