//! End to end: the device simulator (`mbgate sim`) and `mbgate demo` with
//! real peers: socat pty pairs, a raw master on a pty, pymodbus as the master through
//! the gateway, and a terminal for the console.

use crate::common;
use common::sim::{sim, RawLine};
use common::*;
use std::time::{Duration, Instant};

const QUIET: Duration = Duration::from_millis(200);

/// Every byte-exact example of docs/protocol.md §3 against the `cie-m10` profile, from a
/// raw master on the other end of the pty pair: MBAP header included, transaction id
/// echoed, notifications as docs/protocol.md §3 describes them.
#[test]
fn cie_m10_profile_answers_the_protocol_examples_byte_exact() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let s = sim(&socat.dev, &["--loopback", "--notify"]);
    let mut m = RawLine::open(&socat.gw);

    // Inputs are all off at start.
    let read = hex("00 00 00 00 00 06 01 03 00 00 00 01");
    assert_eq!(
        hexs(&m.transact(&read, 11)),
        "00 00 00 00 00 05 01 03 02 00 00"
    );

    // The device manual's write (docs/protocol.md §3): outputs 0 and 4 on. Wired back to the inputs, the change is
    // notified unsolicited as an FC 03 response with transaction id 0.
    let write = hex("00 00 00 00 00 09 01 10 00 08 00 01 02 00 11");
    assert_eq!(
        hexs(&m.transact(&write, 23)),
        "00 00 00 00 00 06 01 10 00 08 00 01 00 00 00 00 00 05 01 03 02 00 11"
    );
    // FC 03 on the output address reads back the outputs; the transaction id is echoed.
    assert_eq!(
        hexs(&m.transact(&hex("12 34 00 00 00 06 01 03 00 08 00 01"), 11)),
        "12 34 00 00 00 05 01 03 02 00 11"
    );

    // All outputs on, so all inputs on: the manual's read reply exactly (docs/protocol.md §3).
    m.transact(&hex("00 00 00 00 00 09 01 10 00 08 00 01 02 00 FF"), 23);
    assert_eq!(
        hexs(&m.transact(&read, 11)),
        "00 00 00 00 00 05 01 03 02 00 FF"
    );

    // Exceptions: 02 for a bad reference, 01 for a function the device lacks.
    let cases = [
        (
            "00 07 00 00 00 06 01 03 00 05 00 01",
            "00 07 00 00 00 03 01 83 02",
        ),
        (
            "00 08 00 00 00 06 01 03 00 00 00 02",
            "00 08 00 00 00 03 01 83 02",
        ),
        (
            "00 09 00 00 00 09 01 10 00 00 00 01 02 00 11",
            "00 09 00 00 00 03 01 90 02",
        ),
        (
            "00 0A 00 00 00 06 01 04 00 00 00 01",
            "00 0A 00 00 00 03 01 84 01",
        ),
        (
            "00 0B 00 00 00 06 01 06 00 08 00 11",
            "00 0B 00 00 00 03 01 86 01",
        ),
    ];
    for (req, want) in cases {
        assert_eq!(hexs(&m.transact(&hex(req), 9)), want, "answer to {req}");
    }

    // Another unit id gets silence; garbage before a request is skipped.
    m.send(&hex("00 0C 00 00 00 06 02 03 00 00 00 01"));
    assert_eq!(m.recv_until_quiet(QUIET, Duration::from_secs(2)), b"");
    m.send(&hex("FF 13 00 00 00 0D 00 00 00 06 01 03 00 00 00 01"));
    assert_eq!(
        hexs(&m.recv(11, Duration::from_secs(5))),
        "00 0D 00 00 00 05 01 03 02 00 FF"
    );
    s.wait_log(
        "rx 00 0C 00 00 00 06 02 03 00 00 00 01 (no such unit: silent)",
        QUIET,
    );
    s.wait_log("tx 00 00 00 00 00 05 01 03 02 00 FF (notification)", QUIET);
}

/// The `generic` profile serves FC 01, 02, 03, 04, 05, 06, 0F, 10 and 17 and their
/// exceptions to pymodbus as the master, through the gateway, over socat.
#[test]
fn generic_profile_serves_pymodbus_through_the_gateway() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _s = sim(
        &socat.dev,
        &[
            "--profile",
            "generic",
            "--units",
            "1,2",
            "--coils",
            "20",
            "--registers",
            "20",
            "--seed",
            "1",
        ],
    );
    let gw = Gateway::start(
        &Cfg::new(&socat.gw)
            .pty_line()
            .relay("response_timeout_ms = 300"),
        dir.path(),
    );

    // The simulator's random discrete inputs come from its seed: the same seed here.
    let expected = mbgate::tools::sim::Device::generic(&[1, 2], 20, 20, 1 + 2);
    let mbgate::tools::sim::Profile::Generic(g) = &expected.profile else {
        unreachable!()
    };
    let discrete: Vec<String> = g.units[&1]
        .discrete
        .iter()
        .map(|b| (if *b { "true" } else { "false" }).to_string())
        .collect();
    let discrete = format!("[{}, false, false, false, false]", discrete.join(", "));

    let steps = r#"[
        ["write_registers", [0, [1, 2, 3]], {"device_id": 1}],
        ["read_holding_registers", [0], {"count": 4, "device_id": 1}],
        ["write_register", [5, 48879], {"device_id": 1}],
        ["read_holding_registers", [5], {"count": 1, "device_id": 1}],
        ["read_input_registers", [6], {"count": 4, "device_id": 1}],
        ["write_coil", [3, true], {"device_id": 1}],
        ["write_coils", [8, [true, false, true]], {"device_id": 1}],
        ["read_coils", [0], {"count": 11, "device_id": 1}],
        ["read_discrete_inputs", [0], {"count": 20, "device_id": 1}],
        ["readwrite_registers", [], {"read_address": 0, "read_count": 3, "write_address": 1, "values": [7], "device_id": 1}],
        ["read_holding_registers", [0], {"count": 1, "device_id": 2}],
        ["read_holding_registers", [20], {"count": 1, "device_id": 1}],
        ["read_coils", [19], {"count": 2, "device_id": 1}],
        ["write_register", [20, 1], {"device_id": 1}],
        ["write_coils", [18, [true, true, true]], {"device_id": 1}],
        ["read_exception_status", [], {"device_id": 1}],
        ["read_holding_registers", [0], {"count": 1, "device_id": 3}]
    ]"#;
    let port = gw.addr.port().to_string();
    let (status, out) = Py::run("master.py", &["--port", &port, steps]);
    assert!(status.success(), "master.py: {out}");
    let want = [
        r#"{"address": 0, "count": 3}"#.to_string(),
        r#"{"registers": [1, 2, 3, 0]}"#.into(),
        r#"{"registers": [48879], "address": 5, "count": 0}"#.into(),
        r#"{"registers": [48879]}"#.into(),
        r#"{"registers": [0, 0, 0, 0]}"#.into(),
        r#"{"bits": [true], "address": 3, "count": 0}"#.into(),
        r#"{"address": 8, "count": 3}"#.into(),
        r#"{"bits": [false, false, false, true, false, false, false, false, true, false, true, false, false, false, false, false]}"#.into(),
        format!(r#"{{"bits": {discrete}}}"#),
        r#"{"registers": [1, 7, 3]}"#.into(),
        r#"{"registers": [0]}"#.into(),
        r#"{"exception": 2}"#.into(),
        r#"{"exception": 2}"#.into(),
        r#"{"exception": 2}"#.into(),
        r#"{"exception": 2}"#.into(),
        r#"{"exception": 1}"#.into(),
        // No device 3 on the line: the gateway answers 0x0B after its timeout.
        r#"{"exception": 11}"#.into(),
    ];
    assert_eq!(out.trim(), format!("[{}]", want.join(", ")));
}

/// Inputs on a schedule (`--toggle-ms`) with change notification: each change reaches
/// a master through a gateway that broadcasts notifications, and a read shows the
/// inputs the last notification announced.
#[test]
fn scheduled_input_changes_are_notified_through_the_gateway() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _s = sim(&socat.dev, &["--toggle-ms", "100", "--notify"]);
    let gw = Gateway::start(
        &Cfg::new(&socat.gw).relay("notifications = \"broadcast\""),
        dir.path(),
    );
    let mut m = gw.connect();
    // The inputs count up by one each time; whichever value the first one shows,
    // the next two follow it.
    let first = read_frame(&mut m);
    assert_eq!(hexs(&first[..10]), "00 00 00 00 00 05 01 03 02 00");
    for k in 1..=2u8 {
        let next = read_frame(&mut m);
        assert_eq!(next[..10], first[..10]);
        assert_eq!(next[10], first[10].wrapping_add(k), "inputs count up");
    }
}

/// Exception 03 comes from the simulator itself when asked directly (through the
/// gateway, mbgate answers out-of-range quantities before they reach the line).
#[test]
fn generic_profile_answers_03_for_bad_values() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _s = sim(&socat.dev, &["--profile", "generic"]);
    let mut m = RawLine::open(&socat.gw);
    let cases = [
        (
            "00 01 00 00 00 06 01 03 00 00 00 00",
            "00 01 00 00 00 03 01 83 03",
        ),
        (
            "00 02 00 00 00 06 01 05 00 00 12 34",
            "00 02 00 00 00 03 01 85 03",
        ),
        (
            "00 03 00 00 00 09 01 10 00 00 00 02 02 00 01",
            "00 03 00 00 00 03 01 90 03",
        ),
        (
            "00 04 00 00 00 06 01 01 00 00 07 D1",
            "00 04 00 00 00 03 01 81 03",
        ),
    ];
    for (req, want) in cases {
        assert_eq!(hexs(&m.transact(&hex(req), 9)), want, "answer to {req}");
    }
}

/// `mbgate demo` from a test: pymodbus reads the inputs and drives the outputs through
/// it, and SIGTERM stops it cleanly.
#[test]
fn demo_serves_pymodbus() {
    let mut d = Proc::start(
        &["demo", "--listen", "127.0.0.1:0", "--loopback"],
        "listening on ",
    );
    let log = d.log();
    let addr = log
        .split("listening on ")
        .nth(1)
        .unwrap()
        .split_whitespace()
        .next()
        .unwrap()
        .to_string();
    let port = addr.rsplit(':').next().unwrap().to_string();
    let steps = r#"[
        ["read_holding_registers", [0], {"count": 1, "device_id": 1}],
        ["write_registers", [8, [17]], {"device_id": 1}],
        ["read_holding_registers", [0], {"count": 1, "device_id": 1}],
        ["read_holding_registers", [8], {"count": 1, "device_id": 1}],
        ["write_register", [8, 1], {"device_id": 1}],
        ["read_holding_registers", [1], {"count": 1, "device_id": 1}]
    ]"#;
    let (status, out) = Py::run("master.py", &["--port", &port, steps]);
    assert!(status.success(), "master.py: {out}");
    assert_eq!(
        out.trim(),
        r#"[{"registers": [0]}, {"address": 8, "count": 1}, {"registers": [17]}, {"registers": [17]}, {"exception": 1}, {"exception": 2}]"#
    );
    let stdout = d.stdout.lock().unwrap().clone();
    assert!(
        stdout.contains(&format!(" read --tcp {addr} holding-registers 0")),
        "the demo says how to connect:\n{stdout}"
    );
    assert!(d.terminate(Duration::from_secs(5)).success());
}

/// Sends 40 read requests back to back to a pipelining simulator with lossy line
/// faults and returns every byte that comes back.
fn lossy_run(seed: &str) -> Vec<u8> {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _s = sim(
        &socat.dev,
        &[
            "--profile",
            "generic",
            "--pipeline",
            "--drop",
            "0.05",
            "--noise",
            "0.01",
            "--seed",
            seed,
        ],
    );
    let mut m = RawLine::open(&socat.gw);
    let burst: Vec<u8> = (1..=40u16).flat_map(|tid| read_req(tid, 1, 0, 3)).collect();
    m.send(&burst);
    m.recv_until_quiet(QUIET, Duration::from_secs(10))
}

/// The line model's faults repeat by seed: the same seed loses the same bytes in both
/// directions, another seed other bytes.
#[test]
fn line_faults_repeat_by_seed() {
    let a = lossy_run("7");
    let b = lossy_run("7");
    let c = lossy_run("8");
    let clean = 40 * (9 + 6);
    assert!(
        !a.is_empty() && a.len() < clean,
        "faults happened: {} of {clean} bytes",
        a.len()
    );
    assert_eq!(hexs(&a), hexs(&b), "same seed, same bytes");
    assert_ne!(a, c, "another seed, other bytes");
}

/// Without --pipeline a request that arrives while the device is busy is ignored, as
/// on the real device; with it, both are answered in turn. --delay-ms and --baud hold
/// each reply back.
#[test]
fn busy_device_pipelining_delay_and_pace() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let two = [read_req(1, 1, 0, 1), read_req(2, 1, 8, 1)].concat();
    {
        let s = sim(&socat.dev, &["--delay-ms", "50"]);
        let mut m = RawLine::open(&socat.gw);
        m.send(&two);
        assert_eq!(
            hexs(&m.recv_until_quiet(QUIET, Duration::from_secs(5))),
            "00 01 00 00 00 05 01 03 02 00 00"
        );
        s.wait_log(
            "rx 00 02 00 00 00 06 01 03 00 08 00 01 (ignored: busy)",
            QUIET,
        );
    }
    {
        let _s = sim(&socat.dev, &["--delay-ms", "50", "--pipeline"]);
        let mut m = RawLine::open(&socat.gw);
        m.send(&two);
        assert_eq!(
            hexs(&m.recv_until_quiet(QUIET, Duration::from_secs(5))),
            "00 01 00 00 00 05 01 03 02 00 00 00 02 00 00 00 05 01 03 02 00 00"
        );
    }
    {
        // 9600 baud, 10 bits a byte: a 12-byte request and an 11-byte reply take
        // 23.96 ms on the wire, plus the 20 ms delay: 10 of them at least 439 ms.
        let _s = sim(&socat.dev, &["--baud", "9600", "--delay-ms", "20"]);
        let mut m = RawLine::open(&socat.gw);
        let start = Instant::now();
        for tid in 1..=10 {
            assert_eq!(m.transact(&read_req(tid, 1, 0, 1), 11).len(), 11);
        }
        let took = start.elapsed();
        assert!(took >= Duration::from_millis(439), "paced: {took:?}");
    }
}

/// The simulator reopens its port when the cable is pulled and plugged back.
#[test]
fn sim_survives_the_cable_being_pulled() {
    let dir = tempdir();
    let mut socat = Socat::start(dir.path());
    let s = sim(&socat.dev, &[]);
    let req = read_req(1, 1, 8, 1);
    assert_eq!(RawLine::open(&socat.gw).transact(&req, 11).len(), 11);
    socat.restart();
    s.wait_log("port lost", Duration::from_secs(5));
    let start = Instant::now();
    loop {
        let mut m = RawLine::open(&socat.gw);
        m.send(&req);
        if m.recv(11, Duration::from_millis(300)) == hex("00 01 00 00 00 05 01 03 02 00 00") {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "not back:\n{}",
            s.log()
        );
    }
}

/// The console on a terminal: the reference simulator's menu (docs/protocol.md §4) as commands, driving what the device
/// answers on the line.
#[test]
fn console_commands_on_a_terminal() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let (status, out) = Py::run(
        "console.py",
        &[
            env!("CARGO_BIN_EXE_mbgate"),
            socat.dev.to_str().unwrap(),
            socat.gw.to_str().unwrap(),
        ],
    );
    assert!(status.success(), "console.py:\n{out}");
    let want = [
        "> inputs 0xA5",
        "inputs 10100101",
        "line: 00 01 00 00 00 05 01 03 02 00 A5",
        "> list",
        "cie-m10 unit 1: inputs 10100101 at register 0, outputs 00000000 at register 8",
        "> input 0 off",
        "inputs 10100100",
        "> log",
        "> add 2",
        "the cie-m10 profile is one device; use --profile generic",
        "> bogus",
        "unknown command `bogus`; `help` lists them",
        "> clear-log",
        "cleared 2 packets",
        "> quit",
        "bye",
        "exit 0",
    ];
    let got: Vec<&str> = out.lines().filter(|l| !l.starts_with("log: ")).collect();
    assert_eq!(got, want, "full transcript:\n{out}");
    // The packet log showed the request and the reply before it was cleared.
    assert!(
        out.contains("log: ") && out.contains(" rx 00 01 00 00 00 06 01 03 00 00 00 01 (request)"),
        "{out}"
    );
    assert!(
        out.contains(" tx 00 01 00 00 00 05 01 03 02 00 A5 (reply)"),
        "{out}"
    );
}

/// Bad simulator options exit 2 and say what is wrong.
#[test]
fn bad_options_exit_2() {
    let out = mbgate(&["sim", "--serial", "/dev/null", "--drop", "2"]);
    assert_eq!(Some(out.code), Some(2));
    assert_eq!(
        out.stderr.trim(),
        "mbgate: --drop is a probability, 0 to 1; not 2"
    );
    let out = mbgate(&["demo", "--profile", "generic", "--loopback"]);
    assert_eq!(Some(out.code), Some(2));
    assert_eq!(
        out.stderr.trim(),
        "mbgate: --loopback applies to the cie-m10 profile only"
    );
}

/// A simulator started before its pty exists (`socat ... &` then `mbgate sim ... &`, as
/// the examples of docs/ run them) paces the pty once it appears: at 9600 baud the
/// reply to an 8-byte RTU request leaves no sooner than the request's and the reply's
/// wire time after it (8 + 9 bytes of 10 bits: 17.7 ms). An unpaced reply, the moment
/// the request is in, would be dropped by a gateway as too early to be its answer.
#[test]
fn a_pty_that_appears_after_the_start_is_paced() {
    let dir = tempdir();
    let dev = dir.path().join("dev");
    let dev_arg = dev.to_str().unwrap().to_owned();
    let mut args = vec!["sim", "--serial", &dev_arg];
    args.extend(common::sim::generic_flags("rtu", "1", "9600"));
    let sim = Proc::start(&args, "cannot open the port");
    let socat = Socat::start(dir.path());
    sim.wait_log("simulating ", Duration::from_secs(5));
    let mut line = RawLine::open(&socat.gw);
    let request = mbgate::frame::rtu::encode(1, &[0x03, 0x00, 0x05, 0x00, 0x02]);
    let start = Instant::now();
    let reply = line.transact(&request, 9);
    let took = start.elapsed();
    let want = mbgate::frame::rtu::encode(1, &[0x03, 0x04, 0x00, 0x05, 0x00, 0x06]);
    assert_eq!(reply, want, "{took:?}");
    assert!(took >= Duration::from_micros(17_700), "unpaced: {took:?}");
}

/// `--pty LINK` replaces only a link (a stale one, from a run that was killed): a file
/// there is the user's, refused by name and left as it was; `--pty` and `--serial`
/// together are a usage error.
#[test]
fn a_pty_link_never_replaces_a_file() {
    let dir = tempdir();
    let file = dir.path().join("notes");
    std::fs::write(&file, b"mine").unwrap();
    let f = file.to_str().unwrap();
    let out = mbgate(&["sim", "--headless", "--pty", f]);
    assert_eq!(out.code, 1, "{}", out.stderr);
    assert!(
        out.stderr
            .contains(&format!("{f} exists and is not a link: not replaced")),
        "{}",
        out.stderr
    );
    assert_eq!(std::fs::read(&file).unwrap(), b"mine");
    let out = mbgate(&["sim", "--pty", f, "--serial", "/dev/null"]);
    assert_eq!(out.code, 2, "{}", out.stderr);
    assert!(out.stderr.contains("cannot be used with"), "{}", out.stderr);
    // A folder that is not there: the link and the system's reason, said once.
    let missing = dir.path().join("missing/x");
    let m = missing.to_str().unwrap();
    let out = mbgate(&["sim", "--headless", "--pty", m]);
    assert_eq!(out.code, 1, "{}", out.stderr);
    let line = out
        .stderr
        .lines()
        .find(|l| l.starts_with("mbgate: cannot link "))
        .unwrap_or_else(|| panic!("{}", out.stderr));
    assert!(
        line.starts_with(&format!("mbgate: cannot link {m} to /dev/pts/")),
        "{line}"
    );
    assert!(
        line.ends_with(": No such file or directory (os error 2)"),
        "{line}"
    );
    assert_eq!(line.matches("No such file").count(), 1, "{line}");
}

/// A simulator whose port nobody reads fills it, and its write waits: SIGTERM still
/// stops it at once (it waited for ever), and its pty's link goes with it. Here the
/// CIE-M10's input change notifications every millisecond fill a pty it made.
#[test]
fn a_port_nobody_reads_does_not_hold_a_stop() {
    let dir = tempdir();
    let link = dir.path().join("plc");
    let l = link.to_str().unwrap();
    let mut s = Proc::start(
        &[
            "sim",
            "--headless",
            "--notify",
            "--toggle-ms",
            "1",
            "--pty",
            l,
        ],
        "made a pty",
    );
    // Until the notifications stop: the pty is full (bounded: it fills in seconds).
    let count = |s: &Proc| s.log().matches("(notification)").count();
    let start = Instant::now();
    let mut last = (count(&s), Instant::now());
    while last.1.elapsed() < Duration::from_millis(500) {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "the pty never filled"
        );
        std::thread::sleep(Duration::from_millis(50));
        let n = count(&s);
        if n != last.0 {
            last = (n, Instant::now());
        }
    }
    assert!(last.0 > 100, "notifications were sent: {}", last.0);
    assert!(s.terminate(Duration::from_secs(5)).success());
    assert!(
        std::fs::symlink_metadata(&link).is_err(),
        "the link is gone"
    );
}
