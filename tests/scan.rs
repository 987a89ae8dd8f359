//! `mbgate scan` (docs/scan.md) against real devices: pymodbus RTU and ASCII serial
//! servers behind the virtual line (`mbgate wire`, so a wrong baud rate or parity
//! garbles as on a cable), at a baud rate, format and unit ids picked at random from a
//! printed seed (MBGATE_SCAN_SEED repeats a run); an empty line; a pymodbus Modbus/TCP
//! server; a port another process holds.

mod common;
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

/// The default scan of an empty line (8 baud rates × 4 formats × 2 framings, units
/// 1-247, leaving each setting after 3 silent units) ends in under two minutes; the
/// time is printed for docs/scan.md.
#[test]
fn the_default_scan_of_an_empty_line_takes_under_two_minutes() {
    let line = Line::start("8N1");
    let t0 = Instant::now();
    // Longer than common::mbgate's 30 s bound: bounded here at 150 s.
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_mbgate"))
        .args(["scan", line.a.to_str().unwrap(), "--json"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if t0.elapsed() > Duration::from_secs(150) {
            let _ = child.kill();
            panic!("the default scan did not end within 150 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let took = t0.elapsed();
    let mut stdout = String::new();
    std::io::Read::read_to_string(&mut child.stdout.take().unwrap(), &mut stdout).unwrap();
    eprintln!("default scan of an empty line: {took:?}");
    assert_eq!(status.code(), Some(1), "{stdout}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(v["found"].as_array().unwrap().len(), 0);
    assert_eq!(v["tries"], 8 * 4 * 2 * 3);
    assert!(took < Duration::from_secs(120), "{took:?}");
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
/// settings) is found right after the three silent tries at 19200 8E1 RTU: 3 tries
/// there, then units 1-20 at 9600 8N1 (FC 03, and FC 04 to each of the 19 silent
/// ones), then its identity (2, or up to 4 when asked again): 44 tries, a few seconds
/// (one fewer FC 04 for each unit whose try heard a late reply of the one before: at
/// least 23). Any other
/// order would put 3 more tries before it for each setting tried first.
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
        (3 + 20..=3 + 20 + 19 + 4).contains(&tries),
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
    let _device = Py::start(
        "lone_device.py",
        &[
            "--port",
            line.b.to_str().unwrap(),
            "--baud",
            "9600",
            "--unit",
            "1",
            "--fixed",
            &hex,
        ],
    );
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
