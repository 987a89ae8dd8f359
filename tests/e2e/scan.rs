//! `mbgate scan` (docs/scan.md) against real devices: pymodbus RTU and ASCII serial
//! servers behind the virtual line (`mbgate wire`, so a wrong baud rate or parity
//! garbles as on a cable), at a baud rate, format and unit ids picked at random from a
//! printed seed (MBGATE_SCAN_SEED repeats a run); an empty line; a pymodbus Modbus/TCP
//! server; a port another process holds.

use crate::common;
use common::*;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// A running `mbgate wire` whose end A is the scanner's (`auto`: the format the scan
/// sets) and end B the device's, at `device_format`.
struct Line {
    _proc: Proc,
    a: PathBuf,
    b: PathBuf,
    _dir: tempfile::TempDir,
}

impl Line {
    fn start(device_format: &str) -> Line {
        let dir = tempdir();
        let a = dir.path().join("scanner");
        let b = dir.path().join("device");
        let proc = Proc::start(
            &[
                "wire",
                a.to_str().unwrap(),
                b.to_str().unwrap(),
                "--a",
                "auto",
                "--b",
                device_format,
            ],
            "ready",
        );
        Line {
            _proc: proc,
            a,
            b,
            _dir: dir,
        }
    }
}

fn seed() -> u64 {
    let seed = std::env::var("MBGATE_SCAN_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(4040);
    eprintln!("MBGATE_SCAN_SEED={seed}");
    seed
}

/// The units of a `--json` report, sorted, with their setting.
fn found(json: &str) -> Vec<(u64, Option<u64>, Option<String>, String)> {
    let v: serde_json::Value = serde_json::from_str(json.trim()).expect(json);
    let mut out: Vec<_> = v["found"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            (
                f["unit"].as_u64().unwrap(),
                f["baud"].as_u64(),
                f["format"].as_str().map(String::from),
                f["framing"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    out.sort();
    out
}

/// One device (two unit ids) at a random format and framing, at `baud`: the scan
/// finds exactly its two units at exactly its setting, and not the two absent ids it
/// is also given; the table's `[[line]]` block has that setting; and the identity
/// pymodbus reports (FC 43/14, FC 17) is shown.
fn finds_the_device_at(baud: u32, rng: &mut fastrand::Rng) {
    let formats = ["8N1", "8E1", "8O1"];
    let format = formats[rng.usize(..formats.len())];
    let framing = ["rtu", "ascii"][rng.usize(..2)];
    let mut ids: Vec<u8> = Vec::new();
    while ids.len() < 4 {
        let id = rng.u8(1..=247);
        if !ids.contains(&id) {
            ids.push(id);
        }
    }
    let (device, absent) = (&ids[..2], &ids[2..]);
    eprintln!("device: {baud} {format} {framing}, units {device:?}; absent {absent:?}");
    let line = Line::start(format);
    let units = device
        .iter()
        .map(u8::to_string)
        .collect::<Vec<_>>()
        .join(",");
    // pyserial's parity stays N: on a pty it cannot be set (the line's --b is the
    // device's format), and Linux refuses pyserial's even parity on a pty.
    let _device = Py::start(
        "serial_device.py",
        &[
            "--port",
            line.b.to_str().unwrap(),
            "--framer",
            framing,
            "--baud",
            &baud.to_string(),
            "--units",
            &units,
        ],
    );
    let mut sorted = ids.clone();
    sorted.sort();
    let scan_units = sorted
        .iter()
        .map(u8::to_string)
        .collect::<Vec<_>>()
        .join(",");
    let a = line.a.to_str().unwrap();
    let t0 = Instant::now();
    let run = mbgate(&[
        "scan",
        a,
        "--baud",
        "9600,115200",
        "--format",
        "8E1,8N1,8O1",
        "--units",
        &scan_units,
        // pymodbus in Python on a loaded machine can take longer than the default
        // 100 ms to answer.
        "--timeout-ms",
        "600",
        "--json",
    ]);
    eprintln!("scan took {:?}: {}", t0.elapsed(), run.stdout);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let mut want: Vec<_> = device
        .iter()
        .map(|&u| {
            (
                u64::from(u),
                Some(u64::from(baud)),
                Some(format.to_string()),
                framing.to_string(),
            )
        })
        .collect();
    want.sort();
    assert_eq!(found(&run.stdout), want);
    let v: serde_json::Value = serde_json::from_str(run.stdout.trim()).unwrap();
    // Its identity, from at least one of its units (pymodbus in Python on a loaded
    // machine can miss a request twice).
    assert!(
        v["found"]
            .as_array()
            .unwrap()
            .iter()
            .any(|f| f["device_id"]["0"] == "pymodbus-test"),
        "{}",
        run.stdout
    );
    // The table form, its [[line]] block ready for mbgate.toml.
    let run = mbgate(&[
        "scan",
        a,
        "--baud",
        &baud.to_string(),
        "--format",
        format,
        "--framing",
        framing,
        "--units",
        &scan_units,
        "--timeout-ms",
        "600",
    ]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let parity = match &format[1..2] {
        "N" => "none",
        "E" => "even",
        _ => "odd",
    };
    let block = format!(
        "[[line]]\nunits = [{}]\nserial = {{ path = \"{a}\", baud_rate = {baud}, data_bits = 8, \
         parity = \"{parity}\", stop_bits = 1, framing = \"{framing}\", flow_control = \"none\" }}",
        {
            let mut d = device.to_vec();
            d.sort();
            d.iter().map(u8::to_string).collect::<Vec<_>>().join(", ")
        }
    );
    assert!(
        run.stdout.contains(&block),
        "{}\nwant:\n{block}",
        run.stdout
    );
    assert!(
        run.stdout.contains("pymodbus-test SCAN 3.16"),
        "{}",
        run.stdout
    );
    // It is a configuration mbgate takes.
    let dir = tempdir();
    let toml = dir.path().join("found.toml");
    let from = run.stdout.find("[[line]]").unwrap();
    std::fs::write(&toml, &run.stdout[from..]).unwrap();
    let check = mbgate(&["check-config", toml.to_str().unwrap()]);
    assert_eq!(check.code, 0, "{}{}", check.stdout, check.stderr);
}

#[test]
fn finds_a_device_at_9600() {
    let mut rng = fastrand::Rng::with_seed(seed());
    finds_the_device_at(9600, &mut rng);
}

#[test]
fn finds_a_device_at_115200() {
    let mut rng = fastrand::Rng::with_seed(seed() + 1);
    finds_the_device_at(115200, &mut rng);
}

/// Nothing on the line: "nothing found" and a hint, exit code 1.
#[test]
fn an_empty_line_finds_nothing_and_says_what_to_check() {
    let line = Line::start("8N1");
    let run = mbgate(&[
        "scan",
        line.a.to_str().unwrap(),
        "--baud",
        "19200",
        "--units",
        "1-5",
    ]);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout.starts_with("nothing found on "),
        "{}",
        run.stdout
    );
    assert!(
        run.stdout.contains("hint: nothing at all came back"),
        "{}",
        run.stdout
    );
    let _ = &line.b;
}

/// `mbgate scan ARGS` bounded at `bound` (common::mbgate's is 30 s): exit code,
/// stdout, time taken. stderr is dropped (the progress bar is off off a terminal).
fn scan_long(args: &[&str], bound: Duration) -> (i32, String, Duration) {
    let t0 = Instant::now();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_mbgate"))
        .arg("scan")
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut out = child.stdout.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = std::io::Read::read_to_string(&mut out, &mut s);
        s
    });
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if t0.elapsed() > bound {
            let _ = child.kill();
            let _ = child.wait();
            panic!("mbgate scan {args:?} did not end within {bound:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let took = t0.elapsed();
    let stdout = reader.join().unwrap();
    eprintln!("$ mbgate scan {}\n{stdout}({took:?})", args.join(" "));
    (status.code().unwrap_or(-1), stdout, took)
}

/// tests/py/lone_device.py on the device's end of `line`: unit `unit` alone, at
/// `baud` (given as the flag's text), with `extra` flags.
fn lone_device(line: &Line, baud: &str, unit: &str, extra: &[&str]) -> Py {
    let mut args = vec![
        "--port",
        line.b.to_str().unwrap(),
        "--baud",
        baud,
        "--unit",
        unit,
    ];
    args.extend_from_slice(extra);
    Py::start("lone_device.py", &args)
}

fn long() -> bool {
    std::env::var_os("MBGATE_LONG").is_some_and(|v| v == "1")
}

/// The default scan of an empty line: every unit at the 8 wide settings (19200 and
/// 9600, 8E1 and 8N1, RTU and ASCII: 8 × 247 tries), 3 units at each of the 56
/// others; the time is printed for docs/scan.md. About three minutes: MBGATE_LONG=1.
#[test]
fn the_default_scan_of_an_empty_line() {
    if !long() {
        eprintln!("skipped: MBGATE_LONG=1 runs it");
        return;
    }
    let line = Line::start("8N1");
    let (code, stdout, took) = scan_long(
        &[line.a.to_str().unwrap(), "--json"],
        Duration::from_secs(400),
    );
    eprintln!("default scan of an empty line: {took:?}");
    assert_eq!(code, 1, "{stdout}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(v["found"].as_array().unwrap().len(), 0);
    assert_eq!(v["tries"], 8 * 247 + 56 * 3);
}

/// Our simulator as a second peer (the proof is the raw device above): one generic
/// device at a unit id drawn from 4-247 and a common setting, found by the default
/// scan.
#[test]
fn a_default_scan_finds_the_simulator_at_any_id() {
    let mut rng = fastrand::Rng::with_seed(seed() + 3);
    let unit = rng.u8(4..=247).to_string();
    let baud = ["19200", "9600"][rng.usize(..2)];
    let (format, parity) = [("8E1", "even"), ("8N1", "none")][rng.usize(..2)];
    eprintln!("simulator: unit {unit} at {baud} {format} rtu");
    let line = Line::start(format);
    let mut flags = common::sim::generic_flags("rtu", &unit, baud);
    flags.extend_from_slice(&["--parity", parity]);
    let _sim = common::sim::sim(&line.b, &flags);
    let (code, stdout, _) = scan_long(
        &[line.a.to_str().unwrap(), "--json"],
        Duration::from_secs(240),
    );
    assert_eq!(code, 0, "{stdout}");
    assert_eq!(
        found(&stdout),
        vec![(
            unit.parse().unwrap(),
            Some(baud.parse().unwrap()),
            Some(format.to_string()),
            "rtu".to_string()
        )]
    );
}

/// A lone device, a raw pyserial one silent for every other unit id, at an id drawn
/// from 4-247 and a common setting (19200 or 9600, 8E1 or 8N1, RTU) from the seed:
/// the default scan, with no option but --json, finds it at that setting, and gives
/// its reply time.
#[test]
fn a_default_scan_finds_a_lone_device_at_any_id() {
    let mut rng = fastrand::Rng::with_seed(seed() + 2);
    let unit = rng.u8(4..=247);
    let baud = [19200, 9600][rng.usize(..2)];
    let format = ["8E1", "8N1"][rng.usize(..2)];
    eprintln!("lone device: unit {unit} at {baud} {format} rtu");
    let line = Line::start(format);
    let _device = lone_device(&line, &baud.to_string(), &unit.to_string(), &[]);
    let (code, stdout, took) = scan_long(
        &[line.a.to_str().unwrap(), "--json"],
        Duration::from_secs(240),
    );
    eprintln!("found unit {unit} at {baud} {format} in {took:?}");
    assert_eq!(code, 0, "{stdout}");
    assert_eq!(
        found(&stdout),
        vec![(
            u64::from(unit),
            Some(baud),
            Some(format.to_string()),
            "rtu".to_string()
        )]
    );
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let f = &v["found"][0];
    // Register 0 holds 1000 (lone_device.py).
    assert_eq!(f["answered"], "FC 03: 1000", "{stdout}");
    assert!(f["replies"].as_u64().unwrap() >= 2, "{stdout}");
    assert!(f["reply_ms_p50"].as_u64().unwrap() <= f["reply_ms_max"].as_u64().unwrap());
}

/// A Modbus/TCP gateway with devices at two unit ids, answering 0x0B for the rest:
/// `--tcp` finds exactly the two.
#[test]
fn tcp_finds_the_units_a_gateway_answers_for() {
    let port = free_port();
    let _server = Py::start(
        "tcp_units.py",
        &["--port", &port.to_string(), "--units", "4,200"],
    );
    let addr = format!("127.0.0.1:{port}");
    let run = mbgate(&["scan", "--tcp", &addr, "--json"]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let units: Vec<u64> = found(&run.stdout).iter().map(|f| f.0).collect();
    assert_eq!(units, vec![4, 200]);
    let run = mbgate(&["scan", "--tcp", &addr, "--units", "1-10"]);
    assert!(
        run.stdout.contains(&format!(
            "[[line]]\nunits = [4]\ntcp = {{ address = \"{addr}\", framing = \"mbap\" }}"
        )),
        "{}",
        run.stdout
    );
}

/// A port another mbgate holds (the simulator, opened exclusively as the gateway
/// opens its port) is refused, naming the process.
#[test]
fn a_held_port_is_refused_naming_who_holds_it() {
    let line = Line::start("8N1");
    let sim = common::sim::sim(
        &line.a,
        &["--profile", "generic", "--framing", "rtu", "--headless"],
    );
    let run = mbgate(&["scan", line.a.to_str().unwrap(), "--baud", "9600"]);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr
            .contains(&format!("held by process {}", sim.pid()))
            || run.stderr.contains(&format!("{} (mbgate)", sim.pid())),
        "{}",
        run.stderr
    );
}

/// Ctrl-C (SIGINT) ends a scan early and prints what it found so far, saying it was
/// interrupted.
#[test]
fn ctrl_c_prints_what_was_found_so_far() {
    let line = Line::start("8N1");
    let _device = Py::start(
        "serial_device.py",
        &[
            "--port",
            line.b.to_str().unwrap(),
            "--baud",
            "9600",
            "--units",
            "1",
        ],
    );
    // Unit 1 first, then 246 silent units at 300 ms each: over a minute.
    let mut scan = Proc::start(
        &[
            "scan",
            line.a.to_str().unwrap(),
            "--baud",
            "9600",
            "--format",
            "8N1",
            "--framing",
            "rtu",
            "--timeout-ms",
            "300",
        ],
        "",
    );
    std::thread::sleep(Duration::from_secs(5));
    let status = scan.stop_with("INT", Duration::from_secs(10));
    assert_eq!(
        status.code(),
        Some(0),
        "{}{}",
        scan.log(),
        scan.stdout.lock().unwrap()
    );
    wait_for("the report", Duration::from_secs(5), || {
        scan.stdout.lock().unwrap().contains("For mbgate.toml")
    });
    let out = scan.stdout.lock().unwrap().clone();
    assert!(out.contains(", interrupted):"), "{out}");
    assert!(out.contains("[[line]]\nunits = [1]\n"), "{out}");
}

/// The default order: a device at 9600 8N1 RTU, unit 1 (one of the two likeliest
/// settings) is found right after the 20 silent tries at 19200 8E1 RTU (a wide
/// setting: every unit): then units 1-20 at 9600 8N1 (FC 03, and FC 04 to each of the
/// 19 silent ones), then its identity (2, or up to 4 when asked again) and 3 timed
/// reads: at most 66 tries, a few seconds (one fewer FC 04 for each unit whose try
/// heard a late reply of the one before: at least 45). Any other order would put 20
/// more tries before it for each wide setting tried first.
#[test]
fn the_default_order_finds_the_usual_settings_first() {
    let line = Line::start("8N1");
    let _device = Py::start(
        "serial_device.py",
        &[
            "--port",
            line.b.to_str().unwrap(),
            "--baud",
            "9600",
            "--units",
            "1",
        ],
    );
    let run = mbgate(&[
        "scan",
        line.a.to_str().unwrap(),
        "--units",
        "1-20",
        "--json",
    ]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert_eq!(
        found(&run.stdout),
        vec![(1, Some(9600), Some("8N1".to_string()), "rtu".to_string())]
    );
    let v: serde_json::Value = serde_json::from_str(run.stdout.trim()).unwrap();
    let tries = v["tries"].as_u64().unwrap();
    assert!(
        (20 + 20 + 2 + 3..=20 + 20 + 19 + 4 + 3).contains(&tries),
        "{}",
        run.stdout
    );
    eprintln!("found at 9600 8N1 in {} s", v["elapsed_s"]);
}

/// A port a running gateway holds is refused, naming the gateway's process.
#[test]
fn a_port_a_gateway_holds_is_refused() {
    let line = Line::start("8N1");
    let cfg = Cfg::new(&line.a)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"");
    let gw = Gateway::start(&cfg, line._dir.path());
    gw.wait_log("serial port open", Duration::from_secs(10));
    let run = mbgate(&["scan", line.a.to_str().unwrap(), "--baud", "9600"]);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("another process holds the port")
            && run.stderr.contains(&format!("{} (mbgate)", gw.proc.pid())),
        "{}",
        run.stderr
    );
}

/// A process that holds the port open without locking it (`exec 3<>PORT`, as a
/// script or a terminal program does) is named, and the port refused, by `scan` and
/// by `run`: both would otherwise read part of each other's bytes. socat, the pty's
/// far side, holds it too and is not named.
#[test]
fn a_port_an_unlocked_process_holds_is_refused_naming_it() {
    let dir = tempdir();
    let cable = Socat::start(dir.path());
    let port = cable.gw.to_str().unwrap().to_string();
    let mut holder = std::process::Command::new("sh")
        .args(["-c", &format!("exec 3<>{port}; exec sleep 60")])
        .spawn()
        .unwrap();
    let pid = holder.id();
    wait_for("the holder", Duration::from_secs(5), || {
        std::fs::read_to_string(format!("/proc/{pid}/comm")).is_ok_and(|c| c.trim() == "sleep")
    });
    let named = format!("held by process {pid} (sleep)");
    let run = mbgate(&["scan", &port, "--baud", "9600", "--units", "1-3"]);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("another process has the port open") && run.stderr.contains(&named),
        "{}",
        run.stderr
    );
    assert!(!run.stdout.contains("nothing found"), "{}", run.stdout);
    let cfg = Cfg::new(&cable.gw)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"");
    let gw = Gateway::start(&cfg, dir.path());
    gw.wait_log(&named, Duration::from_secs(10));
    assert!(!gw.log().contains("serial port open"), "{}", gw.log());
    let _ = holder.kill();
    let _ = holder.wait();
    // Once the holder lets go, the gateway takes the port.
    gw.wait_log("serial port open", Duration::from_secs(10));
}

/// A device that answers every request with one fixed frame of another function
/// (a raw pyserial device, `01 06 00 00 00 2A`): the frames' checks are good, so
/// "nothing found" says frames came that answered no request, with the first one's
/// unit and function, not "no frame with a good check".
#[test]
fn frames_that_answer_no_request_are_named_as_such() {
    let line = Line::start("8N1");
    let fixed = mbgate::frame::rtu::encode(1, &[0x06, 0x00, 0x00, 0x00, 0x2A]);
    let hex: String = fixed.iter().map(|b| format!("{b:02X}")).collect();
    let _device = lone_device(&line, "9600", "1", &["--fixed", &hex]);
    let args = [
        "scan",
        line.a.to_str().unwrap(),
        "--baud",
        "9600",
        "--format",
        "8N1",
        "--framing",
        "rtu",
        "--units",
        "1-3",
        "--timeout-ms",
        "400",
    ];
    let run = mbgate(&args);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout.contains(
            "frames with a good check came back at 9600 8N1 rtu but answered no request \
             (the first: unit 1, FC 06)"
        ),
        "{}",
        run.stdout
    );
    assert!(
        !run.stdout.contains("no frame with a good check"),
        "{}",
        run.stdout
    );
    let mut json = args.to_vec();
    json.push("--json");
    let run = mbgate(&json);
    let v: serde_json::Value = serde_json::from_str(run.stdout.trim()).unwrap();
    assert_eq!(v["unanswering"][0]["function"], 6, "{}", run.stdout);
    assert_eq!(v["garbage"].as_array().unwrap().len(), 0, "{}", run.stdout);
}

/// A Modbus/TCP peer that accepts each connection and closes it at once: the scan
/// says the connection was closed, and stops instead of opening one for each unit.
#[test]
fn tcp_says_when_the_peer_closes_the_connection() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let accepted = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let count = accepted.clone();
    std::thread::spawn(move || {
        for s in listener.incoming().take(50) {
            count.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            drop(s);
        }
    });
    let run = mbgate(&["scan", "--tcp", &addr, "--units", "1-20"]);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout.starts_with("nothing found on "),
        "{}",
        run.stdout
    );
    assert!(
        run.stdout.contains(&format!(
            "{addr} closed the connection without a reply 3 times in a row"
        )),
        "{}",
        run.stdout
    );
    assert!(run.stdout.contains("closes them at once"), "{}", run.stdout);
    assert!(accepted.load(std::sync::atomic::Ordering::SeqCst) <= 4);
}

/// A pymodbus 3.16.1 ASCII server (unit 12, 9600 8N1) that heard garbage with a ':'
/// in it before the scan (":0AZZ", put on the line by pyserial): stock pymodbus keeps
/// it as a frame begun (serial_device.py's clearing after a silence is off), so a
/// request after it is swallowed into a frame whose hex is bad. The scan sends CR LF
/// before its first ASCII request at a setting, which ends that frame: the device is
/// found, at a setting given, with the default settings for unit 12, and (MBGATE_LONG=1)
/// by the whole default scan.
#[test]
fn an_ascii_device_holding_garbage_is_found() {
    let line = Line::start("8N1");
    let _device = Py::start(
        "serial_device.py",
        &[
            "--port",
            line.b.to_str().unwrap(),
            "--framer",
            "ascii",
            "--baud",
            "9600",
            "--units",
            "12",
            "--silence",
            "100000",
        ],
    );
    let a = line.a.to_str().unwrap();
    // With MBGATE_LONG=1, also the whole default scan (every unit, about two
    // minutes before it reaches 9600 8N1 ASCII unit 12).
    let mut runs = vec![
        &["--baud", "9600", "--format", "8N1", "--units", "12"][..],
        &["--units", "12"][..],
    ];
    if long() {
        runs.push(&[][..]);
    }
    for settings in runs {
        let (status, _) = Py::run(
            "serial_send.py",
            &["--port", a, "--baud", "9600", "--hex", "3A30415A5A"],
        );
        assert!(status.success());
        let mut args = vec![a];
        args.extend_from_slice(settings);
        args.push("--json");
        let (code, stdout, _) = scan_long(&args, Duration::from_secs(300));
        assert_eq!(code, 0, "{stdout}");
        assert_eq!(
            found(&stdout),
            vec![(12, Some(9600), Some("8N1".to_string()), "ascii".to_string())]
        );
    }
}

/// A live bus of three ends (tests/py/bus3.py): a pymodbus serial device, a pymodbus
/// master polling it, and the scanner's end behind the virtual line (8N1). Held for
/// the test's length; `counts` is where the bus counts each end's bytes.
struct LiveBus {
    // Dropped in this order: the peers, the bus, its ptys, the virtual line.
    _procs: Vec<Py>,
    _ptys: (Socat, Socat),
    line: Line,
    counts: PathBuf,
    _dirs: (tempfile::TempDir, tempfile::TempDir),
}

impl LiveBus {
    fn start(device: &[&str], master: &[&str]) -> LiveBus {
        let line = Line::start("8N1");
        let (d1, d2) = (tempdir(), tempdir());
        let server = Socat::start(d1.path());
        let client = Socat::start(d2.path());
        let counts = d1.path().join("counts");
        let ends = format!(
            "{},{},{}",
            server.gw.display(),
            client.gw.display(),
            line.b.display()
        );
        let bus = Py::start(
            "bus3.py",
            &[
                "--ends",
                &ends,
                "--baud",
                "9600",
                "--counts",
                counts.to_str().unwrap(),
            ],
        );
        let mut args = vec!["--port", server.dev.to_str().unwrap(), "--baud", "9600"];
        args.extend_from_slice(device);
        let device = Py::start("serial_device.py", &args);
        let mut args = vec!["--port", client.dev.to_str().unwrap(), "--baud", "9600"];
        args.extend_from_slice(master);
        let master = Py::start("rtu_poller.py", &args);
        LiveBus {
            line,
            counts,
            _procs: vec![master, device, bus],
            _ptys: (server, client),
            _dirs: (d1, d2),
        }
    }

    /// The bytes each end has sent onto the bus: the device's, the master's, the
    /// scanner's.
    fn sent(&self) -> Vec<u64> {
        std::fs::read_to_string(&self.counts)
            .unwrap()
            .lines()
            .map(|l| l.split_whitespace().nth(1).unwrap().parse().unwrap())
            .collect()
    }
}

/// Sniffing a live bus: a pymodbus RTU server (units 5 and 9) and a pymodbus client
/// polling it (FC 03 of unit 5, FC 04 of unit 9) on a bus of three ends
/// (tests/py/bus3.py), the third behind the virtual line, at 9600 8N1, where the scan
/// listens. It names the setting, the units and their function codes, and the bus
/// counted no byte from the scan's end.
#[test]
fn listen_names_the_setting_units_and_functions_and_sends_nothing() {
    let bus = LiveBus::start(&["--units", "5,9"], &["--units", "5,9", "--every", "0.05"]);
    let line = &bus.line;
    let (code, stdout, _) = scan_long(
        &[
            line.a.to_str().unwrap(),
            "--listen",
            "--listen-secs",
            "2",
            "--json",
        ],
        Duration::from_secs(120),
    );
    assert_eq!(code, 0, "{stdout}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(v["setting"]["baud"], 9600, "{stdout}");
    assert_eq!(v["setting"]["format"], "8N1", "{stdout}");
    assert_eq!(v["setting"]["framing"], "rtu", "{stdout}");
    let units: Vec<(u64, Vec<u64>)> = v["units"]
        .as_array()
        .unwrap()
        .iter()
        .map(|u| {
            (
                u["unit"].as_u64().unwrap(),
                u["functions"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|f| f.as_u64().unwrap())
                    .collect(),
            )
        })
        .collect();
    assert_eq!(units, vec![(5, vec![3]), (9, vec![4])], "{stdout}");
    for u in v["units"].as_array().unwrap() {
        assert!(u["replies"].as_u64().unwrap() > 0, "{stdout}");
        assert!(u["reply_ms_p50"].is_u64(), "{stdout}");
    }
    assert!(v["requests_per_s"].as_f64().unwrap() > 0.0, "{stdout}");
    // The third end sent nothing onto the bus, while the other two did.
    let sent = bus.sent();
    assert!(sent[0] > 0 && sent[1] > 0, "{sent:?}");
    assert_eq!(sent[2], 0, "the scan's end wrote onto the bus: {sent:?}");
    // The table form names them too.
    let (_, table, _) = scan_long(
        &[
            line.a.to_str().unwrap(),
            "--listen",
            "--listen-secs",
            "2",
            "--baud",
            "9600",
            "--format",
            "8N1",
        ],
        Duration::from_secs(30),
    );
    assert!(
        table.contains("heard on ") && table.contains(" at 9600 8N1 rtu"),
        "{table}"
    );
    assert!(table.contains("units = [5, 9]"), "{table}");
}

/// The timing table of docs/scan.md: a lone raw device at unit 7, 100 and 247, at 9600
/// and 19 200 baud 8N1 RTU, behind the virtual line; the default scan's time to find
/// it (`found_s`) and to end. Some twelve minutes: MBGATE_LONG=1.
#[test]
fn the_time_to_find_a_lone_device() {
    if !long() {
        eprintln!("skipped: MBGATE_LONG=1 runs it");
        return;
    }
    let mut rows = Vec::new();
    for baud in [9600u32, 19200] {
        for unit in [7u8, 100, 247] {
            let line = Line::start("8N1");
            let _device = lone_device(&line, &baud.to_string(), &unit.to_string(), &[]);
            let (code, stdout, took) = scan_long(
                &[line.a.to_str().unwrap(), "--json"],
                Duration::from_secs(300),
            );
            assert_eq!(code, 0, "{stdout}");
            let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
            assert_eq!(v["found"][0]["unit"], unit, "{stdout}");
            assert_eq!(v["found"][0]["baud"], baud, "{stdout}");
            rows.push(format!(
                "| {baud} 8N1 | {unit} | {} s | {:.1} s | {} |",
                v["found"][0]["found_s"],
                took.as_secs_f64(),
                v["tries"]
            ));
        }
    }
    eprintln!("{}", rows.join("\n"));
}

/// A slow lone device (a raw one answering 600 ms after each request): the fast pass
/// finds it by its late reply, its identity and timed reads wait the gateway's default
/// timeout, so its reply times are known (p50 600 ms and more), and the table gives
/// a `[[line.unit]]` block with a `response_timeout_ms` above its longest reply
/// (the line's default, 1000 ms, would cut it short at twice that).
#[test]
fn a_slow_unit_gets_its_reply_time_and_a_unit_block() {
    let line = Line::start("8N1");
    let _device = lone_device(&line, "9600", "9", &["--delay", "0.6"]);
    let (code, stdout, _) = scan_long(
        &[
            line.a.to_str().unwrap(),
            "--baud",
            "9600",
            "--format",
            "8N1",
            "--framing",
            "rtu",
            "--units",
            "1-30",
        ],
        Duration::from_secs(60),
    );
    assert_eq!(code, 0, "{stdout}");
    let row = stdout
        .lines()
        .find(|l| l.starts_with("9 "))
        .unwrap_or_else(|| panic!("{stdout}"));
    let times: Vec<u64> = row
        .split_whitespace()
        .find(|w| w.contains('/'))
        .unwrap()
        .split('/')
        .map(|t| t.parse().unwrap())
        .collect();
    assert!(times[0] >= 600 && times[1] >= times[0], "{stdout}");
    let block = "[[line.unit]]";
    let at = stdout.find(block).unwrap_or_else(|| panic!("{stdout}"));
    let rest = &stdout[at..];
    assert!(
        rest.contains("units = [9]\nresponse_timeout_ms = "),
        "{stdout}"
    );
    let timeout: u64 = rest
        .split("response_timeout_ms = ")
        .nth(1)
        .unwrap()
        .lines()
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(timeout >= 2 * times[1], "{stdout}");
}

/// A master that retries a unit no device answers: a pymodbus master polls unit 5 (a
/// pymodbus device answering in about 8 ms, silent for other ids) and unit 7
/// (nobody), FC 03 of two registers, one every 0.6 s, and sends each unanswered
/// request twice more, 0.6 s apart, byte for byte (a round in 3 s; the listen takes
/// 10 s). The listen lists unit 5 alone, with its replies' time (tens of ms), never
/// the master's retry as unit 7's reply (its shape is a request's) nor the poll gap
/// as unit 5's reply time: RTU and ASCII. (A write's retry, which only its time tells
/// from its echo, is `sniff.rs`'s `a_write_echoed_is_its_reply_and_repeated_is_a_retry`:
/// times as heard on a machine too busy to read the port in time are no premise.)
#[test]
fn listen_never_takes_a_retried_request_for_a_reply() {
    for framer in ["rtu", "ascii"] {
        let bus = LiveBus::start(
            &["--framer", framer, "--units", "5", "--delay", "0.008"],
            &[
                "--framer",
                framer,
                "--units",
                "5,7",
                "--functions",
                "3,3",
                "--every",
                "0.6",
                "--timeout",
                "0.6",
                "--retries",
                "2",
            ],
        );
        let (code, stdout, _) = scan_long(
            &[
                bus.line.a.to_str().unwrap(),
                "--listen",
                "--listen-secs",
                "10",
                "--baud",
                "9600",
                "--format",
                "8N1",
                "--framing",
                framer,
                "--json",
            ],
            Duration::from_secs(60),
        );
        assert_eq!(code, 0, "{framer}: {stdout}");
        let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
        assert_eq!(v["setting"]["framing"], framer, "{stdout}");
        let unit = |n: u64| {
            v["units"]
                .as_array()
                .unwrap()
                .iter()
                .find(|u| u["unit"] == n)
                .unwrap_or_else(|| panic!("{framer}: no unit {n}: {stdout}"))
        };
        let (u5, u7) = (unit(5), unit(7));
        assert_eq!(u7["replies"], 0, "{framer}: {stdout}");
        assert_eq!(
            u7["functions"],
            serde_json::json!([3]),
            "{framer}: {stdout}"
        );
        assert!(u7["requests"].as_u64().unwrap() >= 3, "{framer}: {stdout}");
        assert!(u7["reply_ms_p50"].is_null(), "{framer}: {stdout}");
        let replies = u5["replies"].as_u64().unwrap();
        assert!(replies >= 1, "{framer}: {stdout}");
        // (One more when the listening began between a request and its reply.)
        assert!(replies <= u5["requests"].as_u64().unwrap() + 1, "{stdout}");
        // The device answers in 8 ms and its reply takes some 10 ms (RTU) or 20 ms
        // (ASCII) at 9600; the master's next request comes 600 ms after a reply, its
        // retry 600 ms after a request.
        let p50 = u5["reply_ms_p50"].as_u64().unwrap();
        assert!(p50 < 300, "{framer}: reply p50 {p50} ms: {stdout}");
        // The table's block lists unit 5 alone.
        let (_, table, _) = scan_long(
            &[
                bus.line.a.to_str().unwrap(),
                "--listen",
                "--listen-secs",
                "10",
                "--baud",
                "9600",
                "--format",
                "8N1",
                "--framing",
                framer,
            ],
            Duration::from_secs(60),
        );
        assert!(table.contains("units = [5]\n"), "{framer}: {table}");
        assert_eq!(bus.sent()[2], 0, "the scan's end wrote onto the bus");
    }
}

/// A port with no wire (a pty) that gives bytes as fast as they are written: the
/// listen at a setting takes what a wire at that setting carries in the window (9600
/// baud 8N1, 60 s: 57.6 kB) and judges it then, never holding what a flood of a
/// minute would be. The bus is heard, in a few seconds, not the minute asked.
#[test]
fn listen_on_a_flooding_port_takes_what_a_wire_carries() {
    let dir = tempdir();
    let pty = Socat::start(dir.path());
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let flooding = {
        let stop = stop.clone();
        let mut dev = open_pty(&pty.dev);
        std::thread::spawn(move || {
            use std::io::Write;
            let mut exchange = mbgate::frame::rtu::encode(5, &[3, 0, 0, 0, 1]);
            exchange.extend(mbgate::frame::rtu::encode(5, &[3, 2, 0, 7]));
            let burst = exchange.repeat(256);
            let mut written = 0usize;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                match dev.write(&burst) {
                    Ok(n) => written += n,
                    Err(_) => std::thread::sleep(Duration::from_millis(1)),
                }
            }
            written
        })
    };
    let (code, stdout, took) = scan_long(
        &[
            pty.gw.to_str().unwrap(),
            "--listen",
            "--listen-secs",
            "60",
            "--baud",
            "9600",
            "--format",
            "8N1",
            "--framing",
            "rtu",
            "--json",
        ],
        Duration::from_secs(90),
    );
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let written = flooding.join().unwrap();
    assert_eq!(code, 0, "{stdout}");
    assert!(took < Duration::from_secs(30), "listened {took:?} of 60 s");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(v["units"][0]["unit"], 5, "{stdout}");
    // At most 57 600 bytes, the bound's slack of a read (1024) and the last read
    // (1024) were judged: two frames in 15 bytes.
    let frames = v["frames"].as_u64().unwrap();
    assert!(
        frames > 1000 && frames <= 2 * (57_600 + 2048) / 15,
        "{stdout}"
    );
    eprintln!("{written} bytes written");
}
