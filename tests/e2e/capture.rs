//! Capture to pcapng (docs/capture.md), end to end: the mbgate binary with an RTU line
//! and an MBAP line (socat ptys, scripted raw devices that answer, answer with an
//! exception, answer late, answer with a bad CRC, send garbage), two masters from two
//! addresses and an RTU-over-TCP master; `mbgate capture` reading the control socket;
//! the file read back by Wireshark's tshark (Debian's), the way a user opens it.

use crate::common;

use common::sim::RawLine;
use common::*;
use mbgate::frame::{rtu, Adu};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::os::unix::fs::{MetadataExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// Each packet as tshark decodes it: one row of `fields` a packet (several values of
/// a field joined by commas).
fn tshark(file: &Path, fields: &[&str]) -> Vec<Vec<String>> {
    let mut cmd = Command::new("tshark");
    cmd.args(["-r", file.to_str().unwrap(), "-T", "fields"]);
    cmd.args([
        "-E",
        "separator=/t",
        "-E",
        "occurrence=a",
        "-E",
        "aggregator=,",
    ]);
    for f in fields {
        cmd.args(["-e", f]);
    }
    let out = cmd.output().unwrap_or_else(|e| {
        panic!(
            "tshark: {e} (DEBIAN_FRONTEND=noninteractive apt-get install -y tshark; \
             scripts/test does)"
        )
    });
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "tshark -r {}: {stderr}",
        file.display()
    );
    let text = String::from_utf8(out.stdout).unwrap();
    eprintln!("tshark -r {}:\n{text}", file.display());
    text.lines()
        .map(|l| l.split('\t').map(String::from).collect())
        .collect()
}

/// The addresses the gateway listens on, in the order of its `[[listen]]` tables.
fn listening(gw: &Proc, n: usize) -> Vec<SocketAddr> {
    wait_for("every listener", Duration::from_secs(10), || {
        gw.log().matches("listening on ").count() >= n
    });
    gw.log()
        .split("listening on ")
        .skip(1)
        .map(|rest| rest.split_whitespace().next().unwrap().parse().unwrap())
        .collect()
}

/// A master connected from `local` (an address of 127.0.0.0/8).
fn master_from(local: &str, to: SocketAddr) -> TcpStream {
    use socket2::{Domain, Socket, Type};
    let s = Socket::new(Domain::IPV4, Type::STREAM, None).unwrap();
    s.bind(&local.parse::<SocketAddr>().unwrap().into())
        .unwrap();
    s.connect(&to.into()).unwrap();
    let s: TcpStream = s.into();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s.set_nodelay(true).unwrap();
    s
}

/// The RTU device of line 0 (unit 1): register `a` reads as `a`; FC 06 to 999 gets
/// exception 02; a read at 500 gets a reply whose CRC is wrong; a read at 600 gets
/// its reply 500 ms late (after the timeout and its guard: stale).
fn rtu_device(path: &Path) -> RawRtuDevice {
    let after = |frame: &[u8]| wire_time(frame.len(), 4_000_000) + Duration::from_millis(1);
    RawRtuDevice::scripted(
        path,
        Box::new(move |frame: &[u8]| {
            let Some((1, p)) = rtu::decode(frame) else {
                return vec![];
            };
            let word = |i: usize| u16::from_be_bytes([p[i], p[i + 1]]);
            match (p[0], word(1)) {
                (0x06, 999) => vec![(after(frame), rtu::encode(1, &[0x86, 0x02]))],
                (0x03, addr) => {
                    let mut pdu = vec![0x03, (word(3) * 2) as u8];
                    for a in addr..addr + word(3) {
                        pdu.extend(a.to_be_bytes());
                    }
                    let mut reply = rtu::encode(1, &pdu);
                    match addr {
                        500 => {
                            let n = reply.len();
                            reply[n - 1] ^= 0x5A;
                            vec![(after(frame), reply)]
                        }
                        600 => vec![(Duration::from_millis(500), reply)],
                        _ => vec![(after(frame), reply)],
                    }
                }
                _ => vec![],
            }
        }),
    )
}

/// The MBAP device of line 1 (unit 2): register `a` reads as `a`; FC 16 to 999 gets
/// exception 02; a read at 600 is answered 450 ms late (stale); a read at 700 is
/// answered behind two bytes of garbage (lost sync).
fn mbap_device(path: &Path) -> RawDevice {
    RawDevice::scripted(
        path,
        Box::new(|req: &Adu| {
            let p = req.pdu();
            let word = |i: usize| u16::from_be_bytes([p[i], p[i + 1]]);
            let soon = Duration::from_millis(1);
            match (p[0], word(1)) {
                (0x10, 999) => vec![(
                    soon,
                    Adu::build(req.tid(), 2, &[0x90, 0x02]).as_bytes().to_vec(),
                )],
                (0x03, addr) => {
                    let mut pdu = vec![0x03, (word(3) * 2) as u8];
                    for a in addr..addr + word(3) {
                        pdu.extend(a.to_be_bytes());
                    }
                    let reply = Adu::build(req.tid(), 2, &pdu).as_bytes().to_vec();
                    match addr {
                        600 => vec![(Duration::from_millis(450), reply)],
                        700 => vec![(soon, [&[0xFF, 0x13][..], &reply].concat())],
                        _ => vec![(soon, reply)],
                    }
                }
                _ => vec![],
            }
        }),
    )
}

/// The scripted session's two lines, each a socat pty pair below `dir` with its
/// device on the far end: line 0's RTU device (unit 1), line 1's MBAP device (unit 2).
struct SessionLines {
    _rtu: RawRtuDevice,
    _mbap: RawDevice,
    a: Socat,
    b: Socat,
}

fn session_lines(dir: &Path) -> SessionLines {
    let (a, b) = (dir.join("a"), dir.join("b"));
    std::fs::create_dir_all(&a).unwrap();
    std::fs::create_dir_all(&b).unwrap();
    let (a, b) = (Socat::start(&a), Socat::start(&b));
    SessionLines {
        _rtu: rtu_device(&a.dev),
        _mbap: mbap_device(&b.dev),
        a,
        b,
    }
}

/// The gateway of the scripted session: line 0 RTU (unit 1) and line 1 MBAP (unit
/// 2), a Modbus/TCP listener and an RTU-over-TCP one, the control socket in `dir`.
fn session_gateway(dir: &Path, a: &Socat, b: &Socat, extra: &str) -> (Proc, Vec<SocketAddr>) {
    let line = |s: &Socat, framing: &str, unit: u8| {
        format!(
            "[[line]]\nunits = [{unit}]\n[line.serial]\npath = {:?}\nbaud_rate = 4000000\n\
             silence_floor_ms = 0\nflow_control = \"none\"\nframing = \"{framing}\"\n\
             [line.relay]\nresponse_timeout_ms = 300\n\n",
            s.gw.display().to_string()
        )
    };
    let text = format!(
        "{}{}[[listen]]\naddress = \"127.0.0.1:0\"\n\n[[listen]]\naddress = \"127.0.0.1:0\"\n\
         framing = \"rtu\"\n\n[log]\nlevel = \"debug\"\n\n[control]\nsocket = {:?}\n\n{extra}",
        line(a, "rtu", 1),
        line(b, "mbap", 2),
        dir.join("control.sock").display().to_string(),
    );
    let file = dir.join("mbgate.toml");
    std::fs::write(&file, text).unwrap();
    let gw = Proc::start(
        &["run", "--config", file.to_str().unwrap()],
        "listening on ",
    );
    let addrs = listening(&gw, 2);
    wait_for("the control socket", Duration::from_secs(5), || {
        dir.join("control.sock").exists()
    });
    (gw, addrs)
}

/// A read of register `addr` of `unit` through the session's gateway, asked again
/// (ten tries at most) while it gets 0x0B: the session's lines time out at 300 ms,
/// which a busy machine can exceed; never a wrong value.
fn read_through(m: &mut TcpStream, tid: u16, unit: u8, addr: u16) -> Vec<u8> {
    let timed_out = Adu::exception(tid, unit, 3, 0x0B);
    let mut got = Vec::new();
    for _ in 0..10 {
        got = transact(m, &read_req(tid, unit, addr, 1));
        if got != timed_out.as_bytes() {
            break;
        }
    }
    got
}

fn pdu_req(tid: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    Adu::build(tid, unit, pdu).as_bytes().to_vec()
}

/// `mbgate capture ARGS` running, once it says it is capturing.
fn capture(args: &[&str]) -> Proc {
    Proc::start(args, "capturing to")
}

/// `mbgate capture ARGS` to its end: exit code and stderr.
fn capture_run(args: &[&str], within: Duration) -> (i32, String) {
    let (mut cmd, mut stderr) = Launch::default().command(args);
    let mut child = cmd.spawn().unwrap();
    drop(cmd);
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(start.elapsed() < within, "mbgate {args:?} still running");
        std::thread::sleep(Duration::from_millis(10));
    };
    let mut err = String::new();
    stderr.read_to_string(&mut err).unwrap();
    eprintln!("$ mbgate {}\n{err}", args.join(" "));
    (status.code().unwrap_or(-1), err)
}

/// The column `name` of `rows` read with `fields`.
fn col<'a>(rows: &'a [Vec<String>], fields: &[&str], name: &str) -> Vec<&'a str> {
    let i = fields.iter().position(|f| *f == name).unwrap();
    rows.iter()
        .map(|r| r.get(i).map_or("", String::as_str))
        .collect()
}

#[test]
fn a_scripted_session_through_both_lines_reads_back_in_tshark() {
    if !peer("tshark", "tshark") {
        return;
    }
    let dir = tempdir();
    let lines = session_lines(dir.path());
    let (line_a, line_b) = (&lines.a, &lines.b);
    let (mut gw, addrs) = session_gateway(
        dir.path(),
        line_a,
        line_b,
        "[metrics]\nlisten = \"127.0.0.1:0\"\n",
    );
    let socket = dir.path().join("control.sock");
    let sock = socket.to_str().unwrap();
    let file = dir.path().join("all.pcapng");
    let filtered = dir.path().join("b.pcapng");
    // The status page open before the session: it lists the lines' last frames.
    let http = gw.metrics_addr(Duration::from_secs(5));
    let status = || {
        let mut s = TcpStream::connect(http).unwrap();
        write!(s, "GET /status.json HTTP/1.1\r\n\r\n").unwrap();
        let mut json = String::new();
        s.read_to_string(&mut json).unwrap();
        json
    };
    status();

    let mut all = capture(&["capture", "--socket", sock, "-o", file.to_str().unwrap()]);
    // Master B's reads and only those, until four packets.
    let (mut only_b, mut only_b_err) = Launch::default().command([
        "capture",
        "--socket",
        sock,
        "-o",
        filtered.to_str().unwrap(),
        "--master",
        "127.0.0.2",
        "--function",
        "3",
        "--count",
        "4",
    ]);
    let mut only_b_child = only_b.spawn().unwrap();
    drop(only_b);
    std::thread::sleep(Duration::from_millis(300));

    let mut ma = master_from("127.0.0.1:0", addrs[0]);
    let mut mb = master_from("127.0.0.2:0", addrs[0]);
    let (pa, pb) = (ma.local_addr().unwrap(), mb.local_addr().unwrap());
    // Reads on both lines.
    assert_eq!(
        transact(&mut ma, &read_req(0xA001, 1, 10, 3)),
        read_reply(0xA001, 1, &[10, 11, 12])
    );
    assert_eq!(
        transact(&mut mb, &read_req(0xB001, 2, 20, 2)),
        read_reply(0xB001, 2, &[20, 21])
    );
    // Exceptions from the devices.
    let write_999 = pdu_req(0xA002, 1, &[0x06, 0x03, 0xE7, 0x00, 0x07]);
    assert_eq!(
        transact(&mut ma, &write_999),
        pdu_req(0xA002, 1, &[0x86, 0x02])
    );
    let write_many = write_req(0xB002, 2, 999, &[1, 2]);
    assert_eq!(
        transact(&mut mb, &write_many),
        pdu_req(0xB002, 2, &[0x90, 0x02])
    );
    // MBAP: a reply 450 ms late: 0x0B after 300 ms, then the stale reply is dropped.
    assert_eq!(
        transact(&mut mb, &read_req(0xB003, 2, 600, 1)),
        pdu_req(0xB003, 2, &[0x83, 0x0B])
    );
    std::thread::sleep(Duration::from_millis(300));
    // MBAP: garbage before the reply: dropped, the reply delivered.
    assert_eq!(
        transact(&mut mb, &read_req(0xB004, 2, 700, 1)),
        read_reply(0xB004, 2, &[700])
    );
    // RTU: a reply whose CRC is wrong: 0x0B at once.
    assert_eq!(
        transact(&mut ma, &read_req(0xA003, 1, 500, 1)),
        pdu_req(0xA003, 1, &[0x83, 0x0B])
    );
    // RTU: a reply 500 ms late, after the timeout and the guard: stale.
    assert_eq!(
        transact(&mut ma, &read_req(0xA004, 1, 600, 1)),
        pdu_req(0xA004, 1, &[0x83, 0x0B])
    );
    std::thread::sleep(Duration::from_millis(400));
    // RTU over TCP: a third master, its request and reply as RTU frames.
    let mut mr = master_from("127.0.0.1:0", addrs[1]);
    mr.write_all(&rtu::encode(1, &[0x03, 0x00, 0x1E, 0x00, 0x01]))
        .unwrap();
    let mut reply = [0u8; 7];
    mr.read_exact(&mut reply).unwrap();
    assert_eq!(reply.to_vec(), rtu::encode(1, &[0x03, 0x02, 0x00, 0x1E]));
    std::thread::sleep(Duration::from_millis(200));

    // The filtered capture ended by itself at its count.
    let start = Instant::now();
    let code = loop {
        if let Some(s) = only_b_child.try_wait().unwrap() {
            break s.code();
        }
        assert!(
            start.elapsed() < Duration::from_secs(5),
            "--count 4 did not end it"
        );
        std::thread::sleep(Duration::from_millis(10));
    };
    let mut err = String::new();
    only_b_err.read_to_string(&mut err).unwrap();
    assert_eq!(code, Some(0), "{err}");
    assert!(
        err.contains("4 packets to ") && err.contains("(the count was reached)"),
        "{err}"
    );
    // Ctrl-C ends the other, with its summary.
    let st = all.stop_with("INT", Duration::from_secs(5));
    assert!(st.success(), "{}", all.log());
    assert!(
        all.log().contains("none dropped (stopped)"),
        "{}",
        all.log()
    );

    let fields = [
        "frame.interface_id",
        "frame.interface_name",
        "frame.time_epoch",
        "frame.packet_flags_direction",
        "frame.protocols",
        "ip.src",
        "ip.dst",
        "exported_pdu.src_port",
        "exported_pdu.dst_port",
        "mbtcp.trans_id",
        "mbtcp.unit_id",
        "mbrtu.unit_id",
        "modbus.func_code",
        "modbus.regval_uint16",
        "modbus.exception_code",
        "frame.comment",
    ];
    let rows = tshark(&file, &fields);
    let c = |name: &str| col(&rows, &fields, name);
    let (iface, names, times) = (
        c("frame.interface_id"),
        c("frame.interface_name"),
        c("frame.time_epoch"),
    );
    let (dir_, src, dst, sport) = (
        c("frame.packet_flags_direction"),
        c("ip.src"),
        c("ip.dst"),
        c("exported_pdu.src_port"),
    );
    let (tid, mbtcp_unit, mbrtu_unit, fc, regs, exc, comment) = (
        c("mbtcp.trans_id"),
        c("mbtcp.unit_id"),
        c("mbrtu.unit_id"),
        c("modbus.func_code"),
        c("modbus.regval_uint16"),
        c("modbus.exception_code"),
        c("frame.comment"),
    );
    let on =
        |i: &'static str| -> Vec<usize> { (0..rows.len()).filter(|&r| iface[r] == i).collect() };
    // One interface for the TCP side and one for each line, named.
    for r in 0..rows.len() {
        let want = match iface[r] {
            "0" => "tcp".to_string(),
            "1" => line_a.gw.display().to_string(),
            "2" => line_b.gw.display().to_string(),
            other => panic!("interface {other}"),
        };
        assert_eq!(names[r], want);
    }
    // Times increase on each interface, in microseconds.
    for i in ["0", "1", "2"] {
        let t: Vec<f64> = on(i).iter().map(|&r| times[r].parse().unwrap()).collect();
        assert!(t.len() >= 8, "interface {i}: {t:?}");
        assert!(t.windows(2).all(|w| w[0] <= w[1]), "interface {i}: {t:?}");
        assert!(times[on(i)[0]].ends_with("000"), "µs: {}", times[0]);
    }
    // Both directions on each interface.
    for i in ["0", "1", "2"] {
        for d in ["0x00000001", "0x00000002"] {
            assert!(
                on(i).iter().any(|&r| dir_[r] == d),
                "interface {i} has no {d}"
            );
        }
    }
    // The TCP side: each master by its address and port, with its own transaction ids.
    let query = |r: usize, a: SocketAddr, t: u16, f: u8| {
        src[r] == a.ip().to_string()
            && sport[r] == a.port().to_string()
            && tid[r] == t.to_string()
            && fc[r] == f.to_string()
    };
    for (addr, t, f) in [
        (pa, 0xA001, 3),
        (pb, 0xB001, 3),
        (pa, 0xA002, 6),
        (pb, 0xB002, 16),
        (pb, 0xB004, 3),
    ] {
        assert!(
            on("0").iter().any(|&r| query(r, addr, t, f)),
            "query {t:#x} from {addr}"
        );
        // And the reply back to it, from the gateway's side (port 502 to Wireshark).
        assert!(
            on("0").iter().any(|&r| dst[r] == addr.ip().to_string()
                && sport[r] == "502"
                && tid[r] == t.to_string()),
            "reply {t:#x} to {addr}"
        );
    }
    assert!(on("0")
        .iter()
        .any(|&r| tid[r] == 0xA001.to_string() && regs[r] == "10,11,12"));
    assert!(on("0")
        .iter()
        .any(|&r| tid[r] == 0xB004.to_string() && regs[r] == "700"));
    // The RTU-over-TCP master's frames, as RTU.
    assert!(on("0")
        .iter()
        .any(|&r| c("frame.protocols")[r].ends_with("mbrtu:modbus")
            && mbrtu_unit[r] == "1"
            && regs[r] == "30"));
    // Line 0 (RTU): the request and reply of the read, the exception, the drops.
    let rtu_rows = on("1");
    assert!(rtu_rows
        .iter()
        .any(|&r| mbrtu_unit[r] == "1" && fc[r] == "3" && regs[r] == "10,11,12"));
    assert!(rtu_rows.iter().any(|&r| fc[r] == "6" && exc[r] == "2"));
    assert!(
        rtu_rows
            .iter()
            .any(|&r| comment[r].starts_with("dropped (CRC): ")),
        "no CRC drop"
    );
    assert!(
        rtu_rows
            .iter()
            .any(|&r| comment[r].starts_with("dropped (stale): ")),
        "no stale drop on RTU"
    );
    assert!(rtu_rows
        .iter()
        .any(|&r| comment[r].starts_with("timeout: ")));
    // Line 1 (MBAP): the line's own transaction ids, the exception, the drops.
    let mbap_rows = on("2");
    assert!(mbap_rows
        .iter()
        .any(|&r| mbtcp_unit[r] == "2" && fc[r] == "3" && regs[r] == "20,21"));
    assert!(mbap_rows.iter().any(|&r| fc[r] == "16" && exc[r] == "2"));
    assert!(
        !mbap_rows.iter().any(|&r| tid[r] == 0xB001.to_string()),
        "the line's ids are its own"
    );
    let stale = mbap_rows
        .iter()
        .find(|&&r| comment[r].starts_with("dropped (stale): "))
        .expect("a stale drop");
    assert_eq!(regs[*stale], "600", "the late reply, decoded");
    assert!(mbap_rows
        .iter()
        .any(|&r| comment[r].starts_with("dropped (lost sync): ")));

    // The filtered capture: master B's FC 03 frames, its requests on the line too.
    let fields = ["frame.interface_id", "ip.src", "ip.dst", "modbus.func_code"];
    let rows = tshark(&filtered, &fields);
    assert_eq!(rows.len(), 4);
    for r in &rows {
        assert_eq!(r[3], "3", "{r:?}");
        if r[0] == "0" {
            assert!(r[1] == "127.0.0.2" || r[2] == "127.0.0.2", "{r:?}");
        }
    }
    assert!(
        rows.iter().any(|r| r[0] == "2"),
        "the line's frames for its requests"
    );

    // The status page lists the lines' last frames, from the same packets.
    let json = status();
    assert!(json.contains("\"dir\":\"dropped\""), "{json}");
    assert!(
        json.contains("dropped (stale): a reply to a request already answered or timed out"),
        "{json}"
    );
    assert!(json.contains(&format!("\"master\":\"{pb}\"")), "{json}");
    gw.terminate(Duration::from_secs(10));
}

/// The control socket is its owner's and its group's only (mode 0660): a user who is
/// neither is refused at connect, and, should the mode be loosened, by the gateway
/// itself. A malformed request closes that client only: a capture already running
/// goes on, and so do the masters.
#[test]
fn the_control_socket_refuses_strangers_and_a_bad_request_closes_only_its_client() {
    if !peer("tshark", "tshark") {
        return;
    }
    let dir = tempdir();
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let lines = session_lines(dir.path());
    let (line_a, line_b) = (&lines.a, &lines.b);
    let (mut gw, addrs) = session_gateway(dir.path(), line_a, line_b, "");
    let socket = dir.path().join("control.sock");
    let meta = std::fs::metadata(&socket).unwrap();
    // SAFETY: geteuid(2) has no preconditions and cannot fail.
    let me = unsafe { libc::geteuid() };
    assert_eq!(meta.mode() & 0o7777, 0o660, "srw-rw----");
    assert_eq!(meta.uid(), me, "the gateway's user owns it");
    let sock = socket.to_str().unwrap();

    // A capture running throughout.
    let out = dir.path().join("running.pcapng");
    let mut running = capture(&["capture", "--socket", sock, "-o", out.to_str().unwrap()]);
    let mut m = master_from("127.0.0.1:0", addrs[0]);
    assert_eq!(
        transact(&mut m, &read_req(1, 1, 10, 1)),
        read_reply(1, 1, &[10])
    );

    // Malformed requests: an error and the end of that client, nothing more.
    for bad in [
        &b"capture unit=300\n"[..],
        b"stats\n",
        b"capture line=9\n",
        &[0xFF; 5000],
    ] {
        let mut c = std::os::unix::net::UnixStream::connect(&socket).unwrap();
        c.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let _ = c.write_all(bad);
        let mut answer = String::new();
        let _ = c.read_to_string(&mut answer);
        assert!(answer.starts_with("error: "), "{answer:?}");
        assert!(!answer.contains('\u{0}'));
    }
    // A client that says nothing is closed after its grace, not kept for ever.
    let mut silent = std::os::unix::net::UnixStream::connect(&socket).unwrap();
    silent
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut answer = String::new();
    let _ = silent.read_to_string(&mut answer);
    assert!(answer.contains("no request within"), "{answer:?}");
    assert_eq!(read_through(&mut m, 2, 1, 11), read_reply(2, 1, &[11]));
    let st = running.stop_with("INT", Duration::from_secs(5));
    assert!(st.success(), "{}", running.log());
    let rows = tshark(&out, &["frame.interface_id", "mbtcp.trans_id"]);
    assert!(
        rows.iter().any(|r| r[0] == "0" && r[1] == "2"),
        "the capture went on"
    );

    // Output that fails (a full disk): the capture ends with a clear message, the
    // gateway goes on.
    let (code, err) = capture_run(
        &["capture", "--socket", sock, "-o", "/dev/full"],
        Duration::from_secs(5),
    );
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("cannot write /dev/full: No space left on device"),
        "{err}"
    );
    assert!(err.contains("the gateway goes on"), "{err}");
    assert_eq!(
        transact(&mut m, &read_req(3, 1, 12, 1)),
        read_reply(3, 1, &[12])
    );

    if me != 0 {
        eprintln!("SKIPPED the unprivileged user's part: not root, cannot become nobody");
        gw.terminate(Duration::from_secs(10));
        return;
    }
    // As nobody: the socket's mode refuses at connect.
    let bin = env!("CARGO_BIN_EXE_mbgate");
    let as_nobody = |args: &[&str]| {
        let out = Command::new("setpriv")
            .args(["--reuid=65534", "--regid=65534", "--clear-groups", bin])
            .args(args)
            .output()
            .expect("setpriv (util-linux)");
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let nowhere = dir.path().join("nobody.pcapng");
    let nowhere = nowhere.to_str().unwrap();
    let (code, err) = as_nobody(&["capture", "--socket", sock, "-o", "-", "--count", "1"]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains(&format!("permission denied on {sock}")),
        "{err}"
    );
    // Nor a reload, asked on the same socket.
    let (code, err) = as_nobody(&["reload", "--socket", sock]);
    assert_eq!(code, Some(3), "{err}");
    assert!(
        err.contains(&format!("permission denied on {sock}")),
        "{err}"
    );
    // The mode loosened by hand: the gateway checks who connected.
    std::fs::set_permissions(&socket, std::fs::Permissions::from_mode(0o666)).unwrap();
    let (code, err) = as_nobody(&["capture", "--socket", sock, "-o", nowhere]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("user 65534 may not use the control socket"),
        "{err}"
    );
    assert!(gw
        .log()
        .contains("control socket: user 65534 may not use the control socket"));
    assert_eq!(
        transact(&mut m, &read_req(4, 1, 13, 1)),
        read_reply(4, 1, &[13])
    );
    gw.terminate(Duration::from_secs(10));
}

/// A raw control client: connected, `line` sent (if any), nothing read.
fn control_client(socket: &Path, line: &[u8]) -> std::os::unix::net::UnixStream {
    let mut c = std::os::unix::net::UnixStream::connect(socket).unwrap();
    c.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    c.write_all(line).unwrap();
    c
}

/// Every number a control client sends is checked: `seconds=` past a year (the raw
/// request that made the gateway add 9.3e18 s to its clock) is refused with an error,
/// ten times over, and so is `mbgate capture --seconds 18446744073709551615`; no slot is
/// lost to them. Eight captures whose clients never read are ended once the gateway
/// cannot write to them for 5 s, their slots given back; with eight silent clients
/// connected besides, `mbgate reload` is answered and a new capture runs.
#[test]
fn hostile_and_stalled_control_clients_are_dropped_and_their_slots_given_back() {
    let dir = tempdir();
    let lines = session_lines(dir.path());
    let (mut gw, addrs) = session_gateway(dir.path(), &lines.a, &lines.b, "");
    let socket = dir.path().join("control.sock");
    let sock = socket.to_str().unwrap();

    for _ in 0..10 {
        let mut c = control_client(&socket, b"capture seconds=9300000000000000000\n");
        let mut answer = String::new();
        let _ = c.read_to_string(&mut answer);
        assert_eq!(
            answer,
            "error: seconds=9300000000000000000: at most 31622400\n"
        );
    }
    let out = dir.path().join("never.pcapng");
    let (code, err) = capture_run(
        &[
            "capture",
            "--socket",
            sock,
            "-o",
            out.to_str().unwrap(),
            "--seconds",
            "18446744073709551615",
        ],
        Duration::from_secs(5),
    );
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("seconds=18446744073709551615: at most 31622400"),
        "{err}"
    );

    // Eight captures nobody reads, and traffic enough to fill their sockets: FC 03 of
    // 125 registers from line 1, 8 requests pipelined.
    let stalled: Vec<_> = (0..8)
        .map(|_| control_client(&socket, b"capture\n"))
        .collect();
    gw.wait_log("capture started", Duration::from_secs(5));
    let mut m = master_from("127.0.0.1:0", addrs[0]);
    let start = Instant::now();
    let mut tid = 0u16;
    while gw
        .log()
        .matches("capture ended (the client stopped reading)")
        .count()
        < 8
    {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "captures not read still running:\n{}",
            gw.log()
        );
        for k in 0..8 {
            m.write_all(&read_req(tid.wrapping_add(k), 2, 0, 125))
                .unwrap();
        }
        for _ in 0..8 {
            // The whole reply, or 0x0B where a busy machine held it past the
            // session's 300 ms: traffic is what this needs, never a wrong frame.
            let f = read_frame(&mut m);
            let timed_out = f.len() == 9 && f[7..] == [0x83, 0x0B];
            assert!(f.len() == 9 + 250 || timed_out, "{f:02X?}");
        }
        tid = tid.wrapping_add(8);
    }
    eprintln!(
        "stalled captures ended after {:?}, {tid} reads",
        start.elapsed()
    );

    // Their slots are free: eight clients that say nothing do not keep a reload out,
    // and a capture runs.
    let silent: Vec<_> = (0..8).map(|_| control_client(&socket, b"")).collect();
    let run = mbgate(&["reload", "--socket", sock]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let out = dir.path().join("after.pcapng");
    let after = capture(&[
        "capture",
        "--socket",
        sock,
        "-o",
        out.to_str().unwrap(),
        "--count",
        "2",
    ]);
    assert_eq!(
        transact(&mut m, &read_req(1, 2, 10, 1)),
        read_reply(1, 2, &[10])
    );
    after.wait_log("2 packets to", Duration::from_secs(5));
    drop((stalled, silent));
    gw.terminate(Duration::from_secs(10));
}

/// A socket another user put in a directory anyone may write: the gateway refuses to
/// make its control socket there and says why, and `mbgate reload` and `mbgate
/// capture` run by root check who serves the socket (its peer credentials), refuse
/// the impostor's answer and say why, instead of printing its "ok".
#[test]
fn an_impostor_on_the_control_socket_is_not_believed() {
    // SAFETY: geteuid(2) has no preconditions and cannot fail.
    if unsafe { libc::geteuid() } != 0 {
        eprintln!("SKIPPED: not root, cannot become nobody");
        return;
    }
    let dir = tempdir();
    let open = dir.path().join("open");
    std::fs::create_dir(&open).unwrap();
    std::fs::set_permissions(&open, std::fs::Permissions::from_mode(0o1777)).unwrap();
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let socket = open.join("control.sock");
    let sock = socket.to_str().unwrap();
    // Nobody's socket, answering every client as a gateway that reloaded would.
    struct Killed(std::process::Child);
    impl Drop for Killed {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let _impostor = Killed(
        Command::new("setpriv")
            .args(["--reuid=65534", "--regid=65534", "--clear-groups", "socat"])
            .arg(format!("UNIX-LISTEN:{sock},fork"))
            .arg("SYSTEM:echo ok; echo reloaded: everything")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    );
    wait_for("the impostor's socket", Duration::from_secs(5), || {
        socket.exists()
    });

    let run = mbgate(&["reload", "--socket", sock]);
    assert_eq!(run.code, 3, "{}{}", run.stdout, run.stderr);
    assert!(!run.stdout.contains("reloaded"), "{}", run.stdout);
    assert!(
        run.stderr
            .contains(&format!("{sock} is served by user 65534"))
            && run
                .stderr
                .contains("not the gateway; its answer is not trusted"),
        "{}",
        run.stderr
    );
    let (code, err) = capture_run(
        &[
            "capture",
            "--socket",
            sock,
            "-o",
            dir.path().join("x.pcapng").to_str().unwrap(),
        ],
        Duration::from_secs(5),
    );
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("not the gateway; its answer is not trusted"),
        "{err}"
    );

    // A gateway told to put its control socket there refuses, and says why.
    let lines = session_lines(dir.path());
    let text = format!(
        "[[line]]\n[line.serial]\npath = {:?}\nflow_control = \"none\"\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\n[control]\nsocket = {sock:?}\n",
        lines.a.gw.display().to_string()
    );
    let file = dir.path().join("mbgate.toml");
    std::fs::write(&file, text).unwrap();
    let mut gw = Proc::start(
        &["run", "--config", file.to_str().unwrap()],
        "listening on ",
    );
    gw.wait_log(
        "is writable by everyone (mode 1777): another user could put a socket of their own there",
        Duration::from_secs(5),
    );
    assert!(gw
        .log()
        .contains("mbgate capture and mbgate reload are not available"));
    gw.terminate(Duration::from_secs(10));
}

/// `[capture] file`: every packet into a ring of files of the size asked, the oldest
/// deleted; each file stands alone in tshark. A ring that cannot write (a full disk)
/// stops with one error, and the gateway goes on.
#[test]
fn the_capture_ring_rotates_and_a_full_disk_stops_only_the_ring() {
    if !peer("tshark", "tshark") {
        return;
    }
    let dir = tempdir();
    let lines = session_lines(dir.path());
    let (line_a, line_b) = (&lines.a, &lines.b);
    let ring = dir.path().join("ring.pcapng");
    let extra = format!(
        "[capture]\nfile = {:?}\nfiles = 3\nfile_size_kb = 16\n",
        ring.display().to_string()
    );
    let (mut gw, addrs) = session_gateway(dir.path(), line_a, line_b, &extra);
    // A capture running when the gateway stops: it gets everything to the last
    // packet, then its end.
    let socket = dir.path().join("control.sock");
    let live = dir.path().join("live.pcapng");
    let args = [
        "capture",
        "--socket",
        socket.to_str().unwrap(),
        "-o",
        live.to_str().unwrap(),
    ];
    let (mut cmd, mut live_err) = Launch::default().command(args);
    let mut live_child = cmd.spawn().unwrap();
    drop(cmd);
    wait_for("the capture", Duration::from_secs(5), || {
        gw.log().contains("capture started")
    });
    let mut m = master_from("127.0.0.1:0", addrs[0]);
    // About 70 bytes a packet, four packets a read: 300 reads fill more than three
    // files of 16 kB. The session's lines time out at 300 ms: a read a busy machine
    // delays past that gets 0x0B and is asked again (ten tries), never a wrong value.
    for tid in 0..300u16 {
        let unit = 1 + (tid % 2) as u8;
        assert_eq!(
            read_through(&mut m, tid, unit, tid),
            read_reply(tid, unit, &[tid])
        );
    }
    gw.terminate(Duration::from_secs(10));
    let status = live_child.wait().unwrap();
    let mut err = String::new();
    live_err.read_to_string(&mut err).unwrap();
    assert!(status.success(), "{err}");
    assert!(
        err.contains("1200 packets to ") && err.contains("(the gateway stopped)"),
        "{err}"
    );
    let rows = tshark(&live, &["frame.interface_id", "mbtcp.trans_id"]);
    assert_eq!(rows.len(), 1200);
    let nth = |n: u32| -> PathBuf {
        if n == 0 {
            ring.clone()
        } else {
            PathBuf::from(format!("{}.{n}", ring.display()))
        }
    };
    assert!(!nth(3).exists(), "three files kept");
    let mut last = 0f64;
    for n in [2, 1, 0] {
        let size = std::fs::metadata(nth(n)).unwrap().len();
        assert!(size <= 16 * 1024, "{} is {size} bytes", nth(n).display());
        let rows = tshark(&nth(n), &["frame.time_epoch", "mbtcp.trans_id"]);
        assert!(!rows.is_empty());
        let first: f64 = rows[0][0].parse().unwrap();
        assert!(first >= last, "the ring goes on in time from file to file");
        last = rows.last().unwrap()[0].parse().unwrap();
    }
    let rows = tshark(&ring, &["frame.interface_id", "mbtcp.trans_id"]);
    assert!(
        rows.iter().any(|r| r[0] == "0" && r[1] == "299"),
        "the last read is in the current file"
    );

    // A disk that is full.
    let dir2 = tempdir();
    let lines2 = session_lines(dir2.path());
    let extra = "[capture]\nfile = \"/dev/full\"\n";
    let (mut gw, addrs) = session_gateway(dir2.path(), &lines2.a, &lines2.b, extra);
    let mut m = master_from("127.0.0.1:0", addrs[0]);
    for tid in 0..20u16 {
        assert_eq!(
            transact(&mut m, &read_req(tid, 1, tid, 1)),
            read_reply(tid, 1, &[tid])
        );
    }
    gw.wait_log(
        "capture.file: cannot write /dev/full: No space left on device",
        Duration::from_secs(5),
    );
    assert!(gw
        .log()
        .contains("the capture ring stopped (the gateway goes on)"));
    assert_eq!(
        transact(&mut m, &read_req(99, 2, 5, 1)),
        read_reply(99, 2, &[5])
    );
    gw.terminate(Duration::from_secs(10));
}

/// A Modbus/TCP slave for the master line: one connection at a time, register `a`
/// reads as `a`.
fn tcp_slave() -> (u16, std::thread::JoinHandle<()>) {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let t = std::thread::spawn(move || {
        let Ok((mut s, _)) = listener.accept() else {
            return;
        };
        let mut regs = Registers::default();
        let mut buf = bytes::BytesMut::new();
        let mut chunk = [0u8; 512];
        while let Ok(n) = s.read(&mut chunk) {
            if n == 0 {
                return;
            }
            buf.extend_from_slice(&chunk[..n]);
            while let Ok(Some(req)) = mbgate::frame::mbap::decode_strict(&mut buf) {
                let pdu = regs.answer(req.unit(), req.pdu(), true);
                let reply = Adu::build(req.tid(), req.unit(), &pdu);
                if s.write_all(reply.as_bytes()).is_err() {
                    return;
                }
            }
        }
    });
    (port, t)
}

/// The line whose device is the master (docs/design.md §4.2): the serial master's
/// requests and the replies on the line (RTU), what it sent that was dropped
/// (garbage, a bad CRC: each a frame whose check failed), and the frames to and from the slave on the TCP side.
#[test]
fn the_master_line_and_its_slave_are_captured_too() {
    if !peer("tshark", "tshark") {
        return;
    }
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let (port, _slave) = tcp_slave();
    let socket = dir.path().join("control.sock");
    let text = format!(
        "[[line]]\nrole = \"master\"\nserial = {{ path = {:?}, framing = \"rtu\", \
         baud_rate = 4000000, silence_floor_ms = 0, flow_control = \"none\" }}\n\n\
         [[line.route]]\naddress = \"127.0.0.1:{port}\"\n\n[log]\nlevel = \"debug\"\n\n\
         [control]\nsocket = {:?}\n",
        socat.gw.display().to_string(),
        socket.display().to_string()
    );
    let file = dir.path().join("mbgate.toml");
    std::fs::write(&file, text).unwrap();
    let mut gw = Proc::start(
        &["run", "--config", file.to_str().unwrap()],
        "serial port open",
    );
    gw.wait_log("connected to the slave", Duration::from_secs(5));
    let out = dir.path().join("master.pcapng");
    let mut cap = capture(&[
        "capture",
        "--socket",
        socket.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]);
    let mut line = RawLine::open(&socat.dev);
    // Apart by far more than a busy machine delays the gateway's reads: two frames.
    line.send(&[0xFF, 0x00, 0x13, 0x37]);
    std::thread::sleep(Duration::from_millis(300));
    let mut bad = rtu::encode(1, &[6, 0, 5, 0, 9]);
    bad[6] ^= 0x40;
    line.send(&bad);
    std::thread::sleep(Duration::from_millis(300));
    line.send(&rtu::encode(1, &[3, 0, 5, 0, 2]));
    assert_eq!(
        line.recv(9, Duration::from_secs(2)),
        rtu::encode(1, &[3, 4, 0, 5, 0, 6])
    );
    std::thread::sleep(Duration::from_millis(100));
    assert!(
        cap.stop_with("INT", Duration::from_secs(5)).success(),
        "{}",
        cap.log()
    );
    let fields = [
        "frame.interface_id",
        "frame.packet_flags_direction",
        "ip.dst",
        "exported_pdu.dst_port",
        "mbrtu.unit_id",
        "mbtcp.unit_id",
        "modbus.func_code",
        "modbus.regval_uint16",
        "frame.comment",
    ];
    let rows = tshark(&out, &fields);
    let find = |want: &[(&str, &str)]| {
        rows.iter().any(|r| {
            want.iter()
                .all(|(f, v)| r[fields.iter().position(|x| x == f).unwrap()] == *v)
        })
    };
    // The serial master's request in, its reply out, on the line.
    assert!(find(&[
        ("frame.interface_id", "1"),
        ("frame.packet_flags_direction", "0x00000001"),
        ("mbrtu.unit_id", "1"),
        ("modbus.func_code", "3"),
        ("exported_pdu.dst_port", "502")
    ]));
    assert!(find(&[
        ("frame.interface_id", "1"),
        ("frame.packet_flags_direction", "0x00000002"),
        ("modbus.regval_uint16", "5,6")
    ]));
    // Forwarded to the slave and back, on the TCP side.
    assert!(find(&[
        ("frame.interface_id", "0"),
        ("frame.packet_flags_direction", "0x00000002"),
        ("ip.dst", "127.0.0.1"),
        ("mbtcp.unit_id", "1"),
        ("modbus.func_code", "3")
    ]));
    assert!(find(&[
        ("frame.interface_id", "0"),
        ("frame.packet_flags_direction", "0x00000001"),
        ("modbus.regval_uint16", "5,6")
    ]));
    let comments: Vec<&str> = rows
        .iter()
        .map(|r| r[8].as_str())
        .filter(|c| !c.is_empty())
        .collect();
    // On RTU a frame ends at a silence: the garbage was a 4-byte frame whose CRC
    // failed, as the bad write (8 bytes) was.
    assert_eq!(
        comments,
        [
            "dropped (CRC): a request whose check failed, or cut short (4 bytes)",
            "dropped (CRC): a request whose check failed, or cut short (8 bytes)"
        ]
    );
    gw.terminate(Duration::from_secs(10));
}

/// An ASCII line: the frames on it are given to Wireshark as RTU, decoded, each with
/// its text as it was on the wire in its comment (docs/design.md §6).
#[test]
fn ascii_frames_decode_as_rtu_with_their_text_in_the_comment() {
    if !peer("tshark", "tshark") {
        return;
    }
    use mbgate::frame::ascii;
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    // An ASCII device: a read of register `a` answers `a`.
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let device = {
        let mut pty = open_pty(&socat.dev);
        let stop = stop.clone();
        std::thread::spawn(move || {
            let mut buf = Vec::new();
            let mut chunk = [0u8; 256];
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                match pty.read(&mut chunk) {
                    Ok(n) if n > 0 => buf.extend_from_slice(&chunk[..n]),
                    _ => std::thread::sleep(Duration::from_millis(1)),
                }
                while let Some(end) = buf.windows(2).position(|w| w == b"\r\n") {
                    let frame: Vec<u8> = buf.drain(..end + 2).collect();
                    if let Some((unit, p)) = ascii::decode(&frame) {
                        let addr = u16::from_be_bytes([p[1], p[2]]);
                        let mut pdu = vec![3, 2];
                        pdu.extend(addr.to_be_bytes());
                        std::thread::sleep(Duration::from_millis(1));
                        let _ = pty.write_all(&ascii::encode(unit, &pdu));
                    }
                }
            }
        })
    };
    let socket = dir.path().join("control.sock");
    let cfg = Cfg::new(&socat.gw)
        .pty_line()
        .serial("flow_control = \"none\"")
        .serial("framing = \"ascii\"")
        .control(&format!("socket = {:?}", socket.display().to_string()));
    let mut gw = Gateway::start(&cfg, dir.path());
    gw.wait_log("control socket", Duration::from_secs(5));
    let out = dir.path().join("ascii.pcapng");
    let args = [
        "capture",
        "--socket",
        socket.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ];
    let mut cap = capture(&[&args[..], &["--line", "0", "--count", "2"]].concat());
    let mut m = gw.connect();
    assert_eq!(
        transact(&mut m, &read_req(7, 1, 10, 1)),
        read_reply(7, 1, &[10])
    );
    let start = Instant::now();
    while !cap.log().contains("the count was reached") {
        assert!(start.elapsed() < Duration::from_secs(5), "{}", cap.log());
        std::thread::sleep(Duration::from_millis(10));
    }
    let _ = cap.terminate(Duration::from_secs(5));
    let fields = [
        "frame.protocols",
        "mbrtu.unit_id",
        "modbus.func_code",
        "modbus.regval_uint16",
        "frame.comment",
    ];
    let rows = tshark(&out, &fields);
    assert_eq!(rows.len(), 2, "{rows:?}");
    assert_eq!(rows[0][0], "exported_pdu:mbrtu:modbus");
    assert_eq!(rows[0][4], "ASCII on the wire: :0103000A0001F1\\r\\n");
    assert_eq!(
        (
            rows[1][1].as_str(),
            rows[1][2].as_str(),
            rows[1][3].as_str()
        ),
        ("1", "3", "10")
    );
    assert_eq!(rows[1][4], "ASCII on the wire: :010302000AF0\\r\\n");
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let _ = device.join();
    gw.terminate(Duration::from_secs(10));
}

/// A capture stopped by Ctrl-C the moment traffic ends keeps all of it: 60 reads
/// through an MBAP line make 240 packets (each request and reply on the TCP side and
/// on the line, every one handed to the capture before the master reads its reply),
/// and SIGINT comes as soon as the last reply is read. The file holds the 240, read
/// back by tshark and by the project's reader, and the summary says so: five times
/// over, since where a packet waits when the stop comes is a matter of timing.
#[test]
fn a_capture_stopped_by_ctrl_c_right_after_traffic_keeps_its_tail() {
    if !peer("tshark", "tshark") {
        return;
    }
    let dir = tempdir();
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let lines = session_lines(dir.path());
    let (mut gw, addrs) = session_gateway(dir.path(), &lines.a, &lines.b, "");
    let sock = dir.path().join("control.sock");
    let mut m = master_from("127.0.0.1:0", addrs[0]);
    for round in 0..5u16 {
        let file = dir.path().join(format!("tail-{round}.pcapng"));
        let mut cap = capture(&[
            "capture",
            "--socket",
            sock.to_str().unwrap(),
            "-o",
            file.to_str().unwrap(),
        ]);
        for i in 0..60u16 {
            let tid = round * 100 + i;
            assert_eq!(
                transact(&mut m, &read_req(tid, 2, i, 1)),
                read_reply(tid, 2, &[i])
            );
        }
        let st = cap.stop_with("INT", Duration::from_secs(10));
        assert!(st.success(), "{}", cap.log());
        assert!(
            cap.log().contains("240 packets to ") && cap.log().contains("none dropped (stopped)"),
            "round {round}: {}",
            cap.log()
        );
        let bytes = std::fs::read(&file).unwrap();
        let read = mbgate::ops::capture::pcapng_read::read(&bytes).unwrap();
        assert_eq!(read.damage, None, "round {round}");
        assert_eq!(read.packets.len(), 240, "round {round}");
        let rows = tshark(&file, &["mbtcp.trans_id"]);
        assert_eq!(rows.len(), 240, "round {round}");
        // The last reply to the master is the file's last packet of the TCP side.
        let last = (round * 100 + 59).to_string();
        assert!(
            rows.iter().filter(|r| r[0] == last).count() >= 2,
            "round {round}"
        );
    }
    gw.terminate(Duration::from_secs(10));
}

/// The control socket's slots, each at its bound: eight captures run and a ninth is
/// told so; sixteen clients may wait for their request to be read and the
/// seventeenth is told so; thirty-two at most are being told they were refused, and
/// past them a client is closed at once, unanswered, so no number of connections
/// makes the gateway hold more. The waiting clients' slots come back after their 2 s.
#[test]
fn the_control_socket_s_slots_hold_their_bounds() {
    let dir = tempdir();
    let lines = session_lines(dir.path());
    let (mut gw, _) = session_gateway(dir.path(), &lines.a, &lines.b, "");
    let socket = dir.path().join("control.sock");
    let sock = socket.to_str().unwrap();
    let answer = |mut c: std::os::unix::net::UnixStream| {
        let mut text = String::new();
        let _ = c.read_to_string(&mut text);
        text
    };

    let captures: Vec<_> = (0..8)
        .map(|_| {
            let mut c = control_client(&socket, b"capture\n");
            let mut ok = [0u8; 3];
            c.read_exact(&mut ok).unwrap();
            assert_eq!(&ok, b"ok\n");
            c
        })
        .collect();
    assert_eq!(
        answer(control_client(&socket, b"capture\n")),
        "error: 8 captures are running already\n"
    );

    // Sixteen clients that say nothing hold every waiting slot for their 2 s.
    let waiting: Vec<_> = (0..16).map(|_| control_client(&socket, b"")).collect();
    let busy = "error: 16 clients are waiting to be served already\n";
    // Forty more at once, saying nothing: each refusal waits 0.5 s for what the
    // client sends, so all forty come while thirty-two are being told.
    let more: Vec<_> = (0..40).map(|_| control_client(&socket, b"")).collect();
    let answers: Vec<String> = more.into_iter().map(answer).collect();
    let told = answers.iter().filter(|a| *a == busy).count();
    let unanswered = answers.iter().filter(|a| a.is_empty()).count();
    assert_eq!(told + unanswered, 40, "{answers:?}");
    assert!(
        (32..40).contains(&told),
        "{told} told, {unanswered} closed unanswered"
    );

    // The waiting clients are closed after their 2 s, and their slots given back.
    for c in waiting {
        assert!(answer(c).contains("no request within 2 s"));
    }
    let run = mbgate(&["reload", "--socket", sock]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    drop(captures);
    gw.terminate(Duration::from_secs(10));
}
