//! Reload (SIGHUP, `systemctl reload`; docs/configuration.md "Reload") under load: two masters poll
//! throughout and are never disconnected nor answered wrongly; a shorter response
//! timeout is in force after the reload; the metrics listener starts; a key that needs
//! a restart is said; a broken file is refused with its precise error and the running
//! configuration stays.

use crate::common;
use common::*;
use mbgate::frame::Adu;
use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread;
use std::time::{Duration, Instant};

/// A device that answers a read of one register with its address, at once, except
/// register 9: `slow_ms` later. One request at a time, as a serial device: a request
/// sent while it is busy with register 9 waits for it (at most 500 ms after a 1.5 s
/// timeout, so the pollers never time out).
fn device(path: &std::path::Path, slow_ms: u64) -> RawDevice {
    RawDevice::scripted(
        path,
        Box::new(move |req| {
            let pdu = req.pdu();
            let addr = u16::from_be_bytes([pdu[1], pdu[2]]);
            let [t0, t1] = req.tid().to_be_bytes();
            let [a0, a1] = addr.to_be_bytes();
            let reply = vec![t0, t1, 0, 0, 0, 5, req.unit(), 0x03, 0x02, a0, a1];
            let after = if addr == 9 { slow_ms } else { 0 };
            vec![(Duration::from_millis(after), reply)]
        }),
    )
}

/// A master polling register `addr` until `stop`; returns how many replies it got.
/// Any wrong answer or lost connection panics (and fails the test at the join).
fn poller(gw: &Gateway, addr: u16, stop: Arc<AtomicBool>) -> thread::JoinHandle<u32> {
    let mut m = gw.connect();
    thread::spawn(move || {
        let mut n = 0u32;
        while !stop.load(Ordering::Relaxed) {
            let tid = n as u16;
            assert_eq!(
                transact(&mut m, &read_req(tid, 1, addr, 1)),
                read_reply(tid, 1, &[addr]),
                "poll {n} of register {addr}"
            );
            n += 1;
            thread::sleep(Duration::from_millis(5));
        }
        // Still connected: the gateway answers once more.
        assert_eq!(
            transact(&mut m, &read_req(0, 1, addr, 1)),
            read_reply(0, 1, &[addr])
        );
        n
    })
}

/// How long register 9 takes to answer.
const SLOW_MS: u64 = 2000;

/// Reads register 9 (the slow one): its reply, and how long it took.
fn slow_read(m: &mut std::net::TcpStream, tid: u16) -> (Vec<u8>, Duration) {
    let t0 = Instant::now();
    (transact(m, &read_req(tid, 1, 9, 1)), t0.elapsed())
}

#[test]
fn reload_under_load_applies_the_new_timeout_and_refuses_a_broken_file() {
    // Register 9 answers in 2 s: within the first timeout (8 s), past the reloaded one
    // (1.5 s); the pollers' registers answer at once, and a busy machine delays them
    // by far less than the 1 s left after waiting out register 9.
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _dev = device(&socat.dev, SLOW_MS);
    let base = Cfg::new(&socat.gw)
        .pty_line()
        .serial("flow_control = \"none\"");
    let mut gw = Gateway::start(
        &base.clone().relay("response_timeout_ms = 8000"),
        dir.path(),
    );
    let file = dir.path().join("mbgate.toml");
    gw.wait_log("serial port open", Duration::from_secs(5));
    let stop = Arc::new(AtomicBool::new(false));
    let polls = [poller(&gw, 1, stop.clone()), poller(&gw, 2, stop.clone())];
    let mut m = gw.connect();
    let (reply, _) = slow_read(&mut m, 1);
    assert_eq!(reply, read_reply(1, 1, &[9]), "2 s is within 8 s");

    // A shorter timeout, the metrics listener, and a key only a restart applies.
    let new = base
        .clone()
        .relay("response_timeout_ms = 1500")
        .tcp("max_connections = 5")
        .metrics("listen = \"127.0.0.1:0\"");
    std::fs::write(&file, new.render()).unwrap();
    gw.proc.signal("HUP");
    gw.wait_log("reloaded: ", Duration::from_secs(5));
    // The warning is the line after: read once it has come too.
    gw.wait_log("applied only by a restart", Duration::from_secs(5));
    let log = gw.log();
    assert!(
        log.contains(
            "reloaded: relay.response_timeout_ms = 1500, metrics.listen = \"127.0.0.1:0\""
        ),
        "{log}"
    );
    assert!(
        log.contains("applied only by a restart (systemctl restart): tcp.max_connections = 5"),
        "{log}"
    );
    let (reply, took) = slow_read(&mut m, 2);
    assert_eq!(reply, hex("00 02 00 00 00 03 01 83 0B"), "1.5 s now");
    assert!(took < Duration::from_millis(SLOW_MS), "{took:?}");
    // The metrics listener came up with the reload (its thread says where).
    let http = gw.proc.metrics_addr(Duration::from_secs(5));
    let mut s = std::net::TcpStream::connect(http).unwrap();
    write!(s, "GET /metrics HTTP/1.1\r\n\r\n").unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    assert!(text.starts_with("HTTP/1.1 200 OK"), "{text}");

    // A broken file: refused, with the usual error, and 1.5 s stays.
    let broken = new.relay("retries = \"many\"");
    std::fs::write(&file, broken.render()).unwrap();
    gw.proc.signal("HUP");
    gw.wait_log("reload refused: ", Duration::from_secs(5));
    let log = gw.log();
    let refused = log
        .lines()
        .find(|l| l.contains("reload refused: "))
        .unwrap();
    let line = broken
        .render()
        .lines()
        .position(|l| l.contains("\"many\""))
        .unwrap()
        + 1;
    assert!(
        refused.contains(&format!(
            "reload refused: {}:{line}:11: relay.retries: invalid type: string \"many\", expected an integer; the running configuration stays",
            file.display()
        )),
        "{refused}"
    );
    let (reply, _) = slow_read(&mut m, 3);
    assert_eq!(reply, hex("00 03 00 00 00 03 01 83 0B"), "still 1.5 s");

    stop.store(true, Ordering::Relaxed);
    for p in polls {
        let n = p.join().expect("a poller failed");
        assert!(n >= 3, "{n} polls");
    }
    let counters = gw.stop();
    assert_eq!(counters["connections"], 3, "no master reconnected");
    assert_eq!(counters["protocol_violations"], 0);
}

/// Two lines, each with its own response timeout: the line on `a` 200 ms (its
/// device's 300 ms read times out), the one on `b` `b_timeout` (3000 ms: far more
/// than a busy machine adds to 300 ms). `order` puts the tables
/// in the file: `b_first` writes `b`'s table first; each table keeps its port, units
/// and timeout. The control socket ([`control_socket`]) is beside `a`.
fn two_lines(a: &std::path::Path, b: &std::path::Path, b_first: bool, b_timeout: u32) -> String {
    let table = |path: &std::path::Path, unit: u8, timeout: u32| {
        format!(
            "[[line]]\nunits = [{unit}]\nserial = {{ path = {:?}, baud_rate = 4000000, silence_floor_ms = 0, flow_control = \"none\" }}\nrelay = {{ response_timeout_ms = {timeout} }}\n\n",
            path.display().to_string()
        )
    };
    let (ta, tb) = (table(a, 1, 200), table(b, 2, b_timeout));
    let lines = if b_first { tb + &ta } else { ta + &tb };
    lines
        + "[[listen]]\naddress = \"127.0.0.1:0\"\n\n[log]\nlevel = \"debug\"\n\n\
           [metrics]\nlisten = \"127.0.0.1:0\"\n\n"
        + &format!(
            "[control]\nsocket = {:?}\n",
            control_socket(a).display().to_string()
        )
}

/// The control socket of [`two_lines`] with its first line on `a`.
fn control_socket(a: &std::path::Path) -> std::path::PathBuf {
    a.parent().unwrap().join("control.sock")
}

/// `mbgate reload` over the control socket at `socket`: exit code and output.
fn mbgate_reload(socket: &std::path::Path) -> (i32, String) {
    let run = mbgate(&["reload", "--socket", socket.to_str().unwrap()]);
    (run.code, run.stdout + &run.stderr)
}

/// A reload knows each line by its port, not by its place in the file: the same two
/// tables written in the other order change nothing (before, each line took the
/// other's timeout, and the log said "nothing to change"); a per-line change is
/// applied to that line and named with it, in the log and in `mbgate reload`'s answer
/// (before: "nothing to change"); a file that adds a line is refused, naming it, and
/// the running configuration stays.
#[test]
fn reload_matches_lines_by_their_port_and_names_each_change() {
    let dir = tempdir();
    let (da, db) = (dir.path().join("a"), dir.path().join("b"));
    std::fs::create_dir_all(&da).unwrap();
    std::fs::create_dir_all(&db).unwrap();
    let (sa, sb) = (Socat::start(&da), Socat::start(&db));
    let (_deva, _devb) = (device(&sa.dev, 300), device(&sb.dev, 300));
    let file = dir.path().join("mbgate.toml");
    let gw = Gateway::launch_text(
        &two_lines(&sa.gw, &sb.gw, false, 3000),
        dir.path(),
        Launch::default(),
    );
    gw.wait_log("metrics on http://", Duration::from_secs(5));
    let mut m = gw.connect();
    let slow =
        |m: &mut std::net::TcpStream, tid: u16, unit: u8| transact(m, &read_req(tid, unit, 9, 1));
    let timed_out = |tid: u16, unit: u8| Adu::exception(tid, unit, 0x03, 0x0B).as_bytes().to_vec();
    assert_eq!(slow(&mut m, 1, 1), timed_out(1, 1), "line a: 200 ms");
    assert_eq!(
        slow(&mut m, 2, 2),
        read_reply(2, 2, &[9]),
        "line b: 3000 ms"
    );

    // The same tables, the other way round: SIGHUP.
    std::fs::write(&file, two_lines(&sa.gw, &sb.gw, true, 3000)).unwrap();
    let mut gw = gw;
    gw.proc.signal("HUP");
    gw.wait_log("reloaded: ", Duration::from_secs(5));
    assert_eq!(
        slow(&mut m, 3, 1),
        timed_out(3, 1),
        "line a still 200 ms:\n{}",
        gw.log()
    );
    assert_eq!(
        slow(&mut m, 4, 2),
        read_reply(4, 2, &[9]),
        "line b still 3000 ms"
    );
    let log = gw.log();
    assert!(log.contains("reloaded: nothing to change"), "{log}");
    assert!(!log.contains("applied only by a restart"), "{log}");

    // Line b's timeout to 200 ms, through `mbgate reload`.
    std::fs::write(&file, two_lines(&sa.gw, &sb.gw, true, 200)).unwrap();
    let (code, said) = mbgate_reload(&control_socket(&sa.gw));
    let b = sb.gw.display().to_string();
    let change = format!("reloaded: line {b:?} relay.response_timeout_ms = 200");
    assert_eq!(code, 0, "{said}");
    assert!(said.starts_with(&change), "{said}");
    gw.wait_log(&change, Duration::from_secs(5));
    assert_eq!(slow(&mut m, 5, 2), timed_out(5, 2), "line b: 200 ms now");
    assert_eq!(slow(&mut m, 6, 1), timed_out(6, 1), "line a: 200 ms still");

    // A mistake in the file: `mbgate reload --config` still finds the socket (it reads
    // only control.socket from the file) and says the gateway refused it.
    let good = std::fs::read_to_string(&file).unwrap();
    std::fs::write(&file, good.replace("[log]\n", "[log]\nlevle = \"debug\"\n")).unwrap();
    let run = mbgate(&["reload", "--config", file.to_str().unwrap()]);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("reload refused: ") && run.stderr.contains("log.levle: unknown key"),
        "{}",
        run.stderr
    );

    // A third line: refused, named; the running configuration stays.
    let third = "[[line]]\nunits = [3]\nserial = { path = \"/dev/mbgate-no-such-port\" }\n\n";
    std::fs::write(
        &file,
        third.to_owned() + &two_lines(&sa.gw, &sb.gw, true, 3000),
    )
    .unwrap();
    let (code, said) = mbgate_reload(&control_socket(&sa.gw));
    assert_eq!(code, 1, "{said}");
    assert!(
        said.contains("reload refused: the line on \"/dev/mbgate-no-such-port\" is new in the file: a line is added or removed only by a restart (systemctl restart); the running configuration stays"),
        "{said}"
    );
    assert_eq!(slow(&mut m, 7, 2), timed_out(7, 2), "line b: still 200 ms");
    // The metrics say the last reload was refused (what the alert on it watches,
    // docs/mbgate-alerts.yml), and count them: 2 taken, 2 refused.
    let http = gw.proc.metrics_addr(Duration::from_secs(5));
    let scrape = || {
        let mut s = std::net::TcpStream::connect(http).unwrap();
        write!(s, "GET /metrics HTTP/1.1\r\n\r\n").unwrap();
        let mut text = String::new();
        s.read_to_string(&mut text).unwrap();
        text
    };
    let text = scrape();
    for line in [
        "mbgate_config_last_reload_successful 0.0\n",
        "mbgate_config_reloads_total{result=\"taken\"} 2\n",
        "mbgate_config_reloads_total{result=\"refused\"} 2\n",
    ] {
        assert!(text.contains(line), "{line}{text}");
    }
    let taken_at = |text: &str| -> f64 {
        let line = text
            .lines()
            .find(|l| l.starts_with("mbgate_config_last_reload_success_timestamp_seconds "))
            .expect("the time the file was last taken");
        line.rsplit(' ').next().unwrap().parse().unwrap()
    };
    let before = taken_at(&text);
    // The file mended: taken, and the metrics say so.
    std::fs::write(&file, two_lines(&sa.gw, &sb.gw, true, 200)).unwrap();
    let (code, said) = mbgate_reload(&control_socket(&sa.gw));
    assert_eq!(code, 0, "{said}");
    let text = scrape();
    assert!(
        text.contains("mbgate_config_last_reload_successful 1.0\n"),
        "{text}"
    );
    assert!(
        text.contains("mbgate_config_reloads_total{result=\"taken\"} 3\n"),
        "{text}"
    );
    assert!(taken_at(&text) > before, "{text}");
    let counters = gw.stop();
    assert_eq!(counters["connections"], 1, "no master reconnected");
}

/// `log.traffic` turned on by a reload logs the masters' frames (`master->gw`,
/// `gw->master`) on a connection made before the reload as on one made after it, and
/// turned off again stops them: each connection reads the configuration as it runs,
/// not as it was when the gateway started (before, both kept the start's `false`, and
/// only the line's frames were logged).
#[test]
fn reload_turns_the_traffic_log_on_for_masters_connected_before_it() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _dev = device(&socat.dev, 0);
    let base = Cfg::new(&socat.gw)
        .pty_line()
        .serial("flow_control = \"none\"");
    let mut gw = Gateway::start(&base, dir.path());
    gw.wait_log("serial port open", Duration::from_secs(5));
    let mut before = gw.connect();
    let read = |m: &mut std::net::TcpStream, tid: u16, addr: u16| {
        assert_eq!(
            transact(m, &read_req(tid, 1, addr, 1)),
            read_reply(tid, 1, &[addr])
        );
    };
    read(&mut before, 1, 7);

    let file = dir.path().join("mbgate.toml");
    std::fs::write(&file, base.clone().log("traffic = true").render()).unwrap();
    gw.proc.signal("HUP");
    gw.wait_log("reloaded: ", Duration::from_secs(5));
    assert!(gw.log().contains("log.traffic = true"), "{}", gw.log());
    read(&mut before, 2, 7);
    let mut after = gw.connect();
    read(&mut after, 3, 8);
    for line in [
        "00 02 00 00 00 06 01 03 00 07 00 01 dir=\"master->gw\" conn=1",
        "00 02 00 00 00 05 01 03 02 00 07 dir=\"gw->master\" conn=1",
        "00 03 00 00 00 06 01 03 00 08 00 01 dir=\"master->gw\" conn=2",
        "00 03 00 00 00 05 01 03 02 00 08 dir=\"gw->master\" conn=2",
    ] {
        gw.wait_log(line, Duration::from_secs(5));
    }
    // Before the reload, nothing of the masters' was logged.
    let log = gw.log();
    assert!(
        !log.contains("00 01 00 00 00 06 01 03 00 07 00 01"),
        "{log}"
    );

    // Off again: the connection made while it was on logs no more. SIGUSR1's counters
    // are logged after the reply's line would have been (the traffic line of a frame
    // precedes the frame, and the log is one stream).
    std::fs::write(&file, base.render()).unwrap();
    gw.proc.signal("HUP");
    gw.wait_log("log.traffic = false", Duration::from_secs(5));
    read(&mut after, 4, 8);
    gw.proc.signal("USR1");
    gw.wait_log("counters (SIGUSR1)", Duration::from_secs(5));
    let log = gw.log();
    assert!(
        !log.contains("00 04 00 00 00 06 01 03 00 08 00 01"),
        "{log}"
    );
}
