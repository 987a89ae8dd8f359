//! End to end with third-party peers only, as a user tries a gateway before the
//! hardware comes: pymodbus' own `ModbusSerialServer` as the device (the socket framer,
//! MBAP on the serial line; RTU; ASCII) on socat pty pairs at 9600, 19 200 and 115 200
//! baud, every line of the gateway at its defaults but for its port, framing and speed;
//! the masters pymodbus' `AsyncModbusTcpClient` (FC 01-06, 15, 16 and 23 with exact
//! values, tests/py/tcp_client.py) and Debian's `mbpoll`. Never the project's own
//! simulator. pymodbus answers as soon as a request is in, whatever the baud rate, and
//! its FC 05 and 06 replies are byte for byte the request: a gateway that read the
//! clock against `baud_rate` on a pty refused them (docs/reliability.md, "Knowing the
//! wire").
//!
//! One device process serves all nine ptys and one gateway carries nine lines (units
//! 11 to 19, each remapped to the device's unit 1), so the whole matrix takes seconds.

use crate::common;
use common::*;
use std::time::Duration;

/// The nine lines: framing as pymodbus and mbgate call it, baud, the master's unit.
const LINES: [(&str, &str, u32, u8); 9] = [
    ("socket", "mbap", 9600, 11),
    ("socket", "mbap", 19_200, 12),
    ("socket", "mbap", 115_200, 13),
    ("rtu", "rtu", 9600, 14),
    ("rtu", "rtu", 19_200, 15),
    ("rtu", "rtu", 115_200, 16),
    ("ascii", "ascii", 9600, 17),
    ("ascii", "ascii", 19_200, 18),
    ("ascii", "ascii", 115_200, 19),
];

/// `mbpoll -m tcp -p PORT -a UNIT -0 -1 -o 3 ARGS 127.0.0.1 VALUES`: stdout, and
/// whether it exited 0.
fn mbpoll(port: u16, unit: u8, args: &[&str], values: &[&str]) -> (bool, String) {
    let out = mbpoll_run(port, unit, args, values);
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    (out.status.success(), stdout)
}

/// The `[N]: value` lines of mbpoll's output, as (reference, value).
fn values(out: &str) -> Vec<(u16, i64)> {
    out.lines()
        .filter_map(|l| {
            let (r, v) = l.trim().strip_prefix('[')?.split_once("]:")?;
            Some((r.trim().parse().ok()?, v.trim().parse().ok()?))
        })
        .collect()
}

#[test]
fn third_party_devices_at_every_speed_and_framing_through_default_settings() {
    if !peer("mbpoll", "mbpoll") {
        return;
    }
    let dir = tempdir();
    let socats: Vec<Socat> = (0..LINES.len())
        .map(|i| {
            let d = dir.path().join(format!("line{i}"));
            std::fs::create_dir(&d).unwrap();
            Socat::start(&d)
        })
        .collect();
    let serve: Vec<String> = LINES
        .iter()
        .zip(&socats)
        .map(|((framer, _, baud, _), s)| format!("{framer}:{}:{baud}", s.dev.display()))
        .collect();
    let mut args = Vec::new();
    for s in &serve {
        args.extend(["--serve", s.as_str()]);
    }
    let _devices = Py::start("serial_servers.py", &args);
    let mut text = String::new();
    for ((_, framing, baud, unit), s) in LINES.iter().zip(&socats) {
        text += &format!(
            "[[line]]\nremap = {{ {unit} = 1 }}\n[line.serial]\npath = {:?}\nframing = \"{framing}\"\n\
             baud_rate = {baud}\n\n",
            s.gw.display().to_string()
        );
    }
    text += "[[listen]]\naddress = \"127.0.0.1:0\"\n\n[log]\nlevel = \"debug\"\n";
    let mut gw = Gateway::launch_text(&text, dir.path(), Launch::default());
    for s in &socats {
        gw.wait_log(&format!("path={} ", s.gw.display()), Duration::from_secs(5));
    }
    let log = gw.log();
    assert_eq!(
        log.matches("serial port open: a pseudo-terminal (no wire)")
            .count(),
        LINES.len(),
        "each port found a pty:\n{log}"
    );
    let port = gw.addr.port().to_string();

    // pymodbus' client: every unit at once, each on its own connection.
    let mut py = vec!["--port", port.as_str()];
    let units: Vec<String> = LINES.iter().map(|l| l.3.to_string()).collect();
    for u in &units {
        py.extend(["--unit", u.as_str()]);
    }
    let (status, out) = Py::run("tcp_client.py", &py);
    assert!(status.success(), "tcp_client.py: {out}\n{}", gw.log());
    let steps = out.matches("\"step\"").count();
    assert!(steps >= LINES.len() * 15, "{steps} steps: {out}");

    // mbpoll: reads and writes of each table, single and multiple, exact values.
    let p = gw.addr.port();
    for &(_, framing, baud, unit) in &LINES {
        let at = format!("{framing} at {baud} baud (unit {unit})");
        let (ok, out) = mbpoll(p, unit, &["-t", "4", "-r", "1", "-c", "4"], &[]);
        assert!(ok, "{at}: {out}");
        assert_eq!(
            values(&out),
            [(1, 1001), (2, 1002), (3, 1003), (4, 1004)],
            "{at}: {out}"
        );
        let (ok, out) = mbpoll(p, unit, &["-t", "3", "-r", "0", "-c", "2"], &[]);
        assert!(ok, "{at}: {out}");
        assert_eq!(values(&out), [(0, 2000), (1, 2001)], "{at}: {out}");
        let (ok, out) = mbpoll(p, unit, &["-t", "0", "-r", "0", "-c", "4"], &[]);
        assert!(ok, "{at}: {out}");
        assert_eq!(
            values(&out),
            [(0, 1), (1, 0), (2, 0), (3, 1)],
            "{at}: {out}"
        );
        let (ok, out) = mbpoll(p, unit, &["-t", "1", "-r", "0", "-c", "3"], &[]);
        assert!(ok, "{at}: {out}");
        assert_eq!(values(&out), [(0, 1), (1, 0), (2, 1)], "{at}: {out}");
        // FC 06, then 16; FC 05, then 15: each read back.
        let (ok, out) = mbpoll(p, unit, &["-t", "4", "-r", "90"], &["4321"]);
        assert!(ok && out.contains("Written 1 references"), "{at}: {out}");
        let (ok, out) = mbpoll(p, unit, &["-t", "4", "-r", "100"], &["7", "8", "9"]);
        assert!(ok && out.contains("Written 3 references"), "{at}: {out}");
        let (ok, out) = mbpoll(p, unit, &["-t", "4", "-r", "90", "-c", "13"], &[]);
        assert!(ok, "{at}: {out}");
        let got = values(&out);
        assert_eq!(
            (got[0], &got[10..]),
            ((90, 4321), &[(100, 7), (101, 8), (102, 9)][..]),
            "{at}: {out}"
        );
        let (ok, out) = mbpoll(p, unit, &["-t", "0", "-r", "61"], &["1"]);
        assert!(ok && out.contains("Written 1 references"), "{at}: {out}");
        let (ok, out) = mbpoll(p, unit, &["-t", "0", "-r", "70"], &["0", "1", "1"]);
        assert!(ok && out.contains("Written 3 references"), "{at}: {out}");
        let (ok, out) = mbpoll(p, unit, &["-t", "0", "-r", "61", "-c", "12"], &[]);
        assert!(ok, "{at}: {out}");
        let got: Vec<i64> = values(&out).iter().map(|v| v.1).collect();
        // 61 written on (else off: 61 % 3 != 0), 63 and 66 on as stocked, 69 on,
        // 70..72 written 0 1 1.
        assert_eq!(got, [1, 0, 1, 0, 0, 1, 0, 0, 1, 0, 1, 1], "{at}: {out}");
    }

    let counters = gw.stop();
    for key in [
        "timeouts",
        "dropped_too_early",
        "dropped_echo",
        "dropped_bytes",
    ] {
        assert_eq!(counters[key], 0, "{key}: {counters:?}");
    }
}
