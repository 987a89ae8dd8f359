//! One gateway running a master line beside a line of slaves (docs/design.md §4.2,
//! docs/configuration.md "The device as master"): pymodbus' RTU serial server on one
//! socat pty (the bus), pymodbus' RTU client as the serial master on another, and
//! pymodbus' Modbus/TCP server as the slave the master line reaches. Both lines
//! served at once, both counted on /metrics by their line, and one reload retuning a
//! timeout on each. pymodbus 3.16.1 answers every unit (exception 04 for one it does
//! not have, whatever `ignore_missing_devices` says), so what stays silent for the
//! timeouts is no pymodbus: the bus once its server has stopped, and a second route
//! to a slave that reads and never answers.

use crate::common;
use common::*;
use mbgate::frame::Adu;
use std::io::Read;
use std::net::TcpStream;
use std::path::Path;
use std::thread;
use std::time::{Duration, Instant};

/// The gateway's file: the bus on `bus` (unit 1, `bus_ms` to answer), the master
/// line on `master` (unit 2 to the slave on `silent`, every other unit to the slave
/// on `slave`, `route_ms` to answer), a listener, the metrics and the control socket
/// `socket`.
fn config(
    bus: &Path,
    master: &Path,
    (slave, silent): (u16, u16),
    socket: &Path,
    (bus_ms, route_ms): (u32, u32),
) -> String {
    let serial = |path: &Path| {
        format!(
            "{{ path = {:?}, framing = \"rtu\", baud_rate = 4000000, silence_floor_ms = 0, flow_control = \"none\" }}",
            path.display().to_string()
        )
    };
    format!(
        "[[line]]\nunits = [1]\nserial = {}\nrelay = {{ response_timeout_ms = {bus_ms} }}\n\n\
         [[line]]\nrole = \"master\"\nserial = {}\n\n\
         [[line.route]]\nunits = [2]\naddress = \"127.0.0.1:{silent}\"\nresponse_timeout_ms = {route_ms}\n\n\
         [[line.route]]\naddress = \"127.0.0.1:{slave}\"\nresponse_timeout_ms = {route_ms}\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\n\
         [metrics]\nlisten = \"127.0.0.1:0\"\n\n\
         [control]\nsocket = {:?}\n\n\
         [log]\nlevel = \"debug\"\n",
        serial(bus),
        serial(master),
        socket.display().to_string()
    )
}

/// The gateway's /metrics, read now.
fn scrape(gw: &Gateway) -> String {
    gw.http_get("/metrics")
}

/// The value of `name` (a counter's `_total` sample included) on the line `line`;
/// `None` if the scrape has no such sample.
fn sample(metrics: &str, name: &str, line: &Path) -> Option<f64> {
    let label = format!("line=\"{}\"", line.display());
    metrics
        .lines()
        .filter(|l| {
            l.strip_prefix(name)
                .is_some_and(|rest| rest.starts_with('{') || rest.starts_with("_total{"))
        })
        .find(|l| l.contains(&label))
        .and_then(|l| l.rsplit(' ').next()?.parse().ok())
}

/// pymodbus' RTU client on `port` runs `steps`, timed: its results.
fn serial_master(port: &Path, steps: &str) -> Vec<serde_json::Value> {
    let port = port.to_str().unwrap();
    let (status, out) = Py::run(
        "rtu_master.py",
        &[
            "--port",
            port,
            "--baud",
            "115200",
            "--timeout",
            "10",
            "--timed",
            steps,
        ],
    );
    assert!(status.success(), "rtu_master.py: {out}");
    let got: serde_json::Value = serde_json::from_str(&out).unwrap();
    got.as_array().unwrap().clone()
}

/// A Modbus/TCP slave that takes connections and reads what they send, and never
/// answers; its port.
fn silent_slave() -> u16 {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            thread::spawn(move || {
                let mut stream = stream;
                let mut buf = [0u8; 512];
                while matches!(stream.read(&mut buf), Ok(n) if n > 0) {}
            });
        }
    });
    port
}

/// One read of unit 1 on the bus once nothing answers there: its reply and how long
/// it took.
fn unanswered_on_the_bus(m: &mut TcpStream, tid: u16) -> (Vec<u8>, Duration) {
    let start = Instant::now();
    let reply = transact(m, &read_req(tid, 1, 1, 1));
    (reply, start.elapsed())
}

/// One read by the serial master of unit 2, whose slave never answers: its result,
/// and the seconds it took.
fn unanswered_behind_the_master_line(port: &Path) -> (serde_json::Value, f64) {
    let steps = r#"[["read_holding_registers", [16], {"count": 1, "device_id": 2}]]"#;
    let mut got = serial_master(port, steps);
    let mut one = got.remove(0);
    let seconds = one["seconds"].as_f64().unwrap();
    one.as_object_mut().unwrap().remove("seconds");
    (one, seconds)
}

#[test]
fn a_master_line_beside_a_bus_serves_both_counts_both_and_reloads_both() {
    let dir = tempdir();
    let (db, dm) = (dir.path().join("bus"), dir.path().join("master"));
    std::fs::create_dir_all(&db).unwrap();
    std::fs::create_dir_all(&dm).unwrap();
    let (bus, master) = (Socat::start(&db), Socat::start(&dm));
    // Held open from before the device's start to the end: once the device has
    // stopped, the bus stays a bus where nothing answers (socat would end when the
    // last holder of its device end closed it).
    let _bus_held = std::fs::File::open(&bus.dev).unwrap();
    let serve = format!("rtu:{}:115200", bus.dev.display());
    let device = Py::start("serial_servers.py", &["--serve", &serve]);
    let slave = free_port();
    let _slave = Py::start(
        "tcp_slave.py",
        &["--port", &slave.to_string(), "--unit", "1"],
    );
    let slaves = (slave, silent_slave());
    let socket = dir.path().join("control.sock");
    let file = dir.path().join("mbgate.toml");
    let slow = (2500, 2500);
    let gw = Gateway::launch_text(
        &config(&bus.gw, &master.gw, slaves, &socket, slow),
        dir.path(),
        Launch::default(),
    );
    gw.wait_log(
        "connected to the slave at 127.0.0.1:",
        Duration::from_secs(10),
    );
    let log = gw.log();
    assert!(log.contains("master line on "), "{log}");

    // Both at once: the serial master's reads through the master line while a
    // Modbus/TCP master reads the bus.
    let master_dev = master.dev.clone();
    let steps = r#"[
        ["read_holding_registers", [16], {"count": 2, "device_id": 1}],
        ["read_input_registers", [1], {"count": 2, "device_id": 1}],
        ["write_register", [20, 77], {"device_id": 1}],
        ["read_holding_registers", [20], {"count": 1, "device_id": 1}],
        ["read_coils", [0], {"count": 3, "device_id": 1}],
        ["read_holding_registers", [30], {"count": 3, "device_id": 1}]
    ]"#;
    let serial_side = thread::spawn(move || serial_master(&master_dev, steps));
    let mut m = gw.connect();
    let bus_reads = 20u16;
    for tid in 1..=bus_reads {
        let addr = tid % 5 + 1;
        assert_eq!(
            transact(&mut m, &read_req(tid, 1, addr, 1)),
            read_reply(tid, 1, &[1000 + addr]),
            "bus read {tid}"
        );
    }
    let got = serial_side.join().unwrap();
    let want = serde_json::json!([
        {"registers": [16, 17]},
        {"registers": [501, 502]},
        {"registers": [77], "address": 20},
        {"registers": [77]},
        {"bits": [true, false, false, false, false, false, false, false]},
        {"registers": [30, 31, 32]}
    ]);
    let want = want.as_array().unwrap();
    assert_eq!(got.len(), want.len(), "{got:?}");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        for (k, v) in w.as_object().unwrap() {
            assert_eq!(g.get(k), Some(v), "serial master step {i}: {g} vs {w}");
        }
    }

    // Each line's counts, by its port.
    let metrics = scrape(&gw);
    let on = |name: &str, line: &Path| {
        sample(&metrics, name, line).unwrap_or_else(|| panic!("no {name} for {line:?}:\n{metrics}"))
    };
    assert_eq!(on("mbgate_line_requests", &bus.gw), f64::from(bus_reads));
    assert_eq!(on("mbgate_line_replies", &bus.gw), f64::from(bus_reads));
    assert_eq!(on("mbgate_line_requests", &master.gw), 6.0);
    assert_eq!(on("mbgate_line_replies", &master.gw), 6.0);
    assert_eq!(on("mbgate_line_port_open", &master.gw), 1.0);
    assert_eq!(on("mbgate_line_opens", &master.gw), 1.0);
    assert!(on("mbgate_line_received_bytes", &master.gw) >= 6.0 * 8.0);
    let unit = format!(
        "mbgate_unit_requests_total{{line=\"{}\",unit=\"1\"}} 6",
        master.gw.display()
    );
    assert!(metrics.contains(&unit), "{unit}:\n{metrics}");
    // And on the status page, beside the bus.
    let page: serde_json::Value = serde_json::from_str(&gw.http_get("/status.json")).unwrap();
    let lines = page["lines"].as_array().unwrap();
    let named = |path: &Path| {
        let name = path.to_str().unwrap();
        lines
            .iter()
            .find(|l| l["name"] == name)
            .unwrap_or_else(|| panic!("{name}: {page}"))
    };
    assert_eq!(named(&master.gw)["requests"], 6, "{page}");
    assert_eq!(named(&master.gw)["open"], true, "{page}");
    assert_eq!(named(&bus.gw)["requests"], bus_reads, "{page}");

    // Before the reload: a request nobody answers costs each line its 2.5 s timeout.
    drop(device);
    let timed_out = |tid: u16| Adu::exception(tid, 1, 0x03, 0x0B).as_bytes().to_vec();
    let (reply, took) = unanswered_on_the_bus(&mut m, 100);
    assert_eq!(reply, timed_out(100));
    assert!(took >= Duration::from_millis(2500), "the bus: {took:?}");
    let (result, seconds) = unanswered_behind_the_master_line(&master.dev);
    assert_eq!(result, serde_json::json!({"exception": 11}));
    assert!(seconds >= 2.5, "the master line: {seconds} s");

    // Both timeouts to 300 ms, by one `mbgate reload`.
    std::fs::write(
        &file,
        config(&bus.gw, &master.gw, slaves, &socket, (300, 300)),
    )
    .unwrap();
    let run = mbgate(&["reload", "--socket", socket.to_str().unwrap()]);
    let said = run.stdout + &run.stderr;
    assert_eq!(run.code, 0, "{said}");
    let (b, ml) = (bus.gw.display(), master.gw.display());
    for change in [
        format!("line \"{b}\" relay.response_timeout_ms = 300"),
        format!("line \"{ml}\" route[0].response_timeout_ms = 300"),
        format!("line \"{ml}\" route[1].response_timeout_ms = 300"),
    ] {
        assert!(said.contains(&change), "{change}:\n{said}");
    }
    assert!(!said.contains("applied only by a restart"), "{said}");

    // After it: each line gives up sooner, by a margin no busy machine eats (the
    // lower bound above holds on any machine).
    let (reply, took) = unanswered_on_the_bus(&mut m, 101);
    assert_eq!(reply, timed_out(101));
    assert!(took < Duration::from_millis(2500), "the bus: {took:?}");
    let (result, seconds) = unanswered_behind_the_master_line(&master.dev);
    assert_eq!(result, serde_json::json!({"exception": 11}));
    assert!(seconds < 2.5, "the master line: {seconds} s");

    let metrics = scrape(&gw);
    assert_eq!(sample(&metrics, "mbgate_line_timeouts", &bus.gw), Some(2.0));
    assert_eq!(
        sample(&metrics, "mbgate_line_timeouts", &master.gw),
        Some(2.0)
    );

    // A relay key on the master line means nothing there (its timeouts are its
    // routes'): the reload is refused naming file, line and key, and what runs stays.
    let relay_on_master = config(&bus.gw, &master.gw, slaves, &socket, (300, 300)).replacen(
        "role = \"master\"\n",
        "role = \"master\"\nrelay = { response_timeout_ms = 5000 }\n",
        1,
    );
    std::fs::write(&file, relay_on_master).unwrap();
    let run = mbgate(&["reload", "--socket", socket.to_str().unwrap()]);
    let said = run.stdout + &run.stderr;
    assert_ne!(run.code, 0, "{said}");
    let want = format!(
        "{}:8:33: line[1].relay.response_timeout_ms: means nothing on a master line",
        file.display()
    );
    assert!(said.contains(&want), "{want}:\n{said}");
    let (result, seconds) = unanswered_behind_the_master_line(&master.dev);
    assert_eq!(result, serde_json::json!({"exception": 11}));
    assert!(
        seconds < 2.5,
        "still 300 ms on the master line: {seconds} s"
    );
    let mut gw = gw;
    let counters = gw.stop();
    assert_eq!(counters["connections"], 1, "the master was never cut off");
}

/// A gateway whose only line is a master line has no listener, and runs until it is
/// stopped: past its drain's bound (the route's 100 ms and two seconds), the serial
/// master is still served; SIGHUP reloads it (its default action would end the
/// process); it shuts down only at SIGTERM.
#[test]
fn a_lone_master_line_runs_until_stopped() {
    let dir = tempdir();
    let master = Socat::start(dir.path());
    let slave = free_port();
    let _slave = Py::start(
        "tcp_slave.py",
        &["--port", &slave.to_string(), "--unit", "1"],
    );
    let text = |timeout: u32| {
        format!(
            "[[line]]\nrole = \"master\"\nserial = {{ path = {:?}, framing = \"rtu\", baud_rate = 4000000, silence_floor_ms = 0, flow_control = \"none\" }}\n\n\
             [[line.route]]\naddress = \"127.0.0.1:{slave}\"\nresponse_timeout_ms = {timeout}\n\n[log]\nlevel = \"debug\"\n",
            master.gw.display().to_string()
        )
    };
    let file = dir.path().join("mbgate.toml");
    std::fs::write(&file, text(100)).unwrap();
    let mut gw = Proc::start(
        &["run", "--config", file.to_str().unwrap()],
        "serial port open",
    );
    gw.wait_log(
        "connected to the slave at 127.0.0.1:",
        Duration::from_secs(10),
    );
    thread::sleep(Duration::from_secs(3));
    // Registers 16 and 17 read through the master line, from the pymodbus slave.
    let reads_16_17 = |gw: &Proc| {
        let steps = r#"[["read_holding_registers", [16], {"count": 2, "device_id": 1}]]"#;
        let got = serial_master(&master.dev, steps);
        assert_eq!(
            got[0]["registers"],
            serde_json::json!([16, 17]),
            "{}",
            gw.log()
        );
    };
    reads_16_17(&gw);
    std::fs::write(&file, text(300)).unwrap();
    gw.signal("HUP");
    gw.wait_log(
        "reloaded: route[0].response_timeout_ms = 300",
        Duration::from_secs(5),
    );
    reads_16_17(&gw);
    let log = gw.log();
    assert!(!log.contains("listening on"), "{log}");
    assert!(!log.contains("shutting down"), "before SIGTERM:\n{log}");
    let status = gw.terminate(Duration::from_secs(10));
    assert!(status.success(), "{}", gw.log());
    assert!(gw.log().contains("shutting down"), "{}", gw.log());
}
