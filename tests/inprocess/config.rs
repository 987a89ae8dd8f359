//! The configuration contract (docs/design.md §4): defaults, every error message with
//! its file, line, column and key, the command-line flags over the file, and the
//! docs/configuration.md's table and config/mbgate.toml held to the declarations.

use clap::Parser;
use mbgate::cli::overrides::Overrides;
use mbgate::config::*;
use std::path::Path;

const F: &str = "config/test.toml";

fn err(text: &str) -> String {
    parse(text, F).expect_err("should be rejected").to_string()
}

/// The message names the file, the line and the key.
#[track_caller]
fn assert_err(text: &str, line: usize, key: &str, contains: &str) {
    let e = err(text);
    let at = format!("{F}:{line}:");
    assert!(e.starts_with(&at), "{e:?} should start with {at:?}");
    assert!(e.contains(&format!(": {key}: ")), "{e:?} should name {key}");
    assert!(e.contains(contains), "{e:?} should contain {contains:?}");
}

#[test]
fn defaults_are_the_documented_ones() {
    let c = Config::default();
    assert_eq!(c.lines[0].serial.path, "/dev/ttyUSB0");
    assert_eq!(c.lines[0].serial.baud_rate, 19200);
    assert_eq!(c.lines[0].serial.data_bits, 8);
    assert_eq!(c.lines[0].serial.parity, Parity::None);
    assert_eq!(c.lines[0].serial.stop_bits, 1);
    assert_eq!(c.lines[0].serial.flow_control, FlowControl::Hardware);
    assert_eq!(c.lines[0].serial.framing, Framing::Mbap);
    assert_eq!(c.listeners[0].tcp.listen, "0.0.0.0:502".parse().unwrap());
    assert_eq!(c.listeners[0].tcp.max_connections, 32);
    assert_eq!(c.listeners[0].tcp.idle_timeout_ms, 60_000);
    assert_eq!(c.lines[0].relay.response_timeout_ms, 1000);
    assert_eq!(c.lines[0].relay.frame_gap_ms, 50);
    assert_eq!(c.lines[0].relay.max_in_flight, 1);
    assert_eq!(c.lines[0].relay.max_pending_per_connection, 16);
    assert_eq!(c.lines[0].relay.queue_depth, 64);
    assert_eq!(c.lines[0].relay.retries, 0);
    assert!(!c.lines[0].relay.retry_writes);
    assert_eq!(c.lines[0].relay.notifications, Notifications::Drop);
    assert_eq!(c.lines[0].serial.silence_floor_ms, Floor::Auto);
    assert_eq!(c.lines[0].serial.port_kind, PortKind::Auto);
    assert!(c.lines[0].serial.low_latency && !c.lines[0].relay.device_notifications);
    assert!(!c.lines[0].serial.rs485 && !c.lines[0].serial.echo);
    assert_eq!(c.lines[0].relay.broadcast_delay_ms, 100);
    assert_eq!(c.lines[0].relay.broadcast_reply, BroadcastReply::None);
    assert!(c.lines[0].relay.unit_backoff);
    assert_eq!(c.lines[0].relay.unit_backoff_after, 3);
    assert_eq!(
        (
            c.lines[0].relay.unit_backoff_ms,
            c.lines[0].relay.unit_backoff_max_ms
        ),
        (1000, 30_000)
    );
    assert_eq!(
        (
            c.lines[0].relay.probe_timeout_ms,
            c.lines[0].relay.timeout_guard_ms
        ),
        (250, 100)
    );
    assert_eq!(c.log.level, "info");
    assert!(!c.log.traffic);
}

#[test]
fn empty_file_is_defaults() {
    assert_eq!(parse("", F).unwrap(), Config::default());
    assert_eq!(parse("\n# nothing\n\n", F).unwrap(), Config::default());
    assert_eq!(
        parse("[serial]\n[tcp]\n[relay]\n[log]\n", F).unwrap(),
        Config::default()
    );
}

#[test]
fn shipped_file_is_defaults() {
    let text = include_str!("../../config/mbgate.toml");
    assert_eq!(
        parse(text, "config/mbgate.toml").unwrap(),
        Config::default()
    );
    // Every key is spelled out in the shipped file.
    let printed = to_toml(&Config::default());
    for line in printed.lines().filter(|l| l.contains(" = ")) {
        let key = line.split(" = ").next().unwrap();
        assert!(
            text.lines().any(|l| l.starts_with(&format!("{key} = "))),
            "{key} missing from config/mbgate.toml"
        );
    }
}

#[test]
fn partial_section_keeps_other_defaults() {
    let c = parse(
        "[serial]\nbaud_rate = 9600\nparity = \"even\"\n[relay]\nnotifications = \"broadcast\"\n",
        F,
    )
    .unwrap();
    let mut want = Config::default();
    want.lines[0].serial.baud_rate = 9600;
    want.lines[0].serial.parity = Parity::Even;
    want.lines[0].relay.notifications = Notifications::Broadcast;
    assert_eq!(c, want);
}

#[test]
fn dotted_keys_and_inline_tables_work() {
    let c = parse(
        "serial.baud_rate = 9600\ntcp = { max_connections = 4 }\n",
        F,
    )
    .unwrap();
    assert_eq!(c.lines[0].serial.baud_rate, 9600);
    assert_eq!(c.listeners[0].tcp.max_connections, 4);
}

#[test]
fn syntax_error_names_file_line_column() {
    let e = err("[serial]\nbaud_rate = 19200\npath = \"/dev/ttyS0\n");
    assert!(e.starts_with(&format!("{F}:3:")), "{e}");
    assert!(e.contains("serial.path: TOML syntax error"), "{e}");

    let e = err("[serial]\n\n\nbaud_rate = = 5\n");
    assert!(
        e.starts_with(&format!("{F}:4:13: serial.baud_rate: ")),
        "{e}"
    );

    let e = err("[serial\n");
    assert!(e.starts_with(&format!("{F}:1:")), "{e}");
    assert!(e.contains("TOML syntax error"), "{e}");
}

#[test]
fn duplicate_key_is_an_error() {
    let e = err("[tcp]\nmax_connections = 3\nmax_connections = 4\n");
    assert!(e.starts_with(&format!("{F}:3:")), "{e}");
    assert!(e.contains("tcp.max_connections"), "{e}");
}

#[test]
fn unknown_key_in_each_section() {
    assert_err(
        "[serial]\nbaudrate = 9600\n",
        2,
        "serial.baudrate",
        "unknown key; expected one of path, baud_rate, data_bits, parity, stop_bits, \
         flow_control, framing, port_kind, low_latency, silence_floor_ms, inter_frame_gap_us, rs485, \
         rs485_delay_before_send_ms, rs485_delay_after_send_ms, echo, direction, \
         direction_invert, direction_gpio_chip, direction_gpio_line, direction_delay_before_us, \
         direction_delay_after_us (did you mean `baud_rate`?)",
    );
    assert_err(
        "[tcp]\nlisten = \"0.0.0.0:502\"\n\nmax_conections = 3\n",
        4,
        "tcp.max_conections",
        "unknown key; expected one of listen, max_connections, idle_timeout_ms",
    );
    assert_err(
        "[relay]\ntimeout_ms = 3\n",
        2,
        "relay.timeout_ms",
        "unknown key; expected one of response_timeout_ms,",
    );
    assert_err(
        "[log]\nlevel = \"info\"\ncolour = true\n",
        3,
        "log.colour",
        "unknown key; expected one of level, traffic",
    );
    assert_err(
        "[serial]\n[modbus]\nunit = 1\n",
        2,
        "modbus",
        "unknown key; expected one of serial, tcp, relay, log",
    );
    assert_err(
        "[serial]\n[tcp]\n[relay]\n[log]\n[logs]\n",
        5,
        "logs",
        "(did you mean `log`?)",
    );
}

#[test]
fn unknown_key_column_points_at_key() {
    let e = err("[serial]\n  baudrate = 9600\n");
    assert!(e.starts_with(&format!("{F}:2:3: serial.baudrate: ")), "{e}");
}

#[test]
fn wrong_types() {
    assert_err(
        "[serial]\nbaud_rate = \"fast\"\n",
        2,
        "serial.baud_rate",
        "invalid type: string \"fast\", expected an integer",
    );
    assert_err(
        "[serial]\npath = 5\n",
        2,
        "serial.path",
        "expected a string",
    );
    assert_err(
        "[relay]\nretry_writes = \"yes\"\n",
        2,
        "relay.retry_writes",
        "invalid type",
    );
    assert_err("[tcp]\nlisten = 502\n", 2, "tcp.listen", "0.0.0.0:502");
    assert_err("[log]\ntraffic = 1\n", 2, "log.traffic", "invalid type");
    assert_err(
        "[relay]\nframe_gap_ms = 1.5\n",
        2,
        "relay.frame_gap_ms",
        "integer",
    );
    assert_err(
        "serial = 5\n",
        1,
        "serial",
        "invalid type: integer `5`, expected a table ([section])",
    );
    assert_err(
        "[serial]\nparity = 1\n",
        2,
        "serial.parity",
        "expected a string, one of none, even, odd",
    );
    assert_err(
        "[relay]\nqueue_depth = 99999999999999999999\n",
        2,
        "relay.queue_depth",
        "must be between 1 and 65536",
    );
}

#[test]
fn bad_enum_values() {
    assert_err(
        "[serial]\nparity = \"mark\"\n",
        2,
        "serial.parity",
        "invalid value \"mark\"; expected one of none, even, odd",
    );
    assert_err(
        "[serial]\nflow_control = \"rts\"\n",
        2,
        "serial.flow_control",
        "expected one of hardware, software, none",
    );
    assert_err(
        "[serial]\nframing = \"tcp\"\n",
        2,
        "serial.framing",
        "invalid value \"tcp\"; expected one of mbap, rtu, ascii",
    );
    assert_err(
        "[relay]\nnotifications = \"all\"\n",
        2,
        "relay.notifications",
        "expected one of drop, broadcast",
    );
    assert_err(
        "[serial]\nparity = \"Even\"\n",
        2,
        "serial.parity",
        "invalid value",
    );
}

#[test]
fn range_violations() {
    let cases: &[(&str, &str, &str, &str)] = &[
        (
            "serial",
            "baud_rate",
            "49",
            "must be between 50 and 4000000, got 49",
        ),
        (
            "serial",
            "baud_rate",
            "4000001",
            "must be between 50 and 4000000",
        ),
        (
            "serial",
            "baud_rate",
            "-1",
            "must be between 50 and 4000000, got -1",
        ),
        ("serial", "data_bits", "6", "must be 7 or 8, got 6"),
        ("serial", "data_bits", "300", "must be 7 or 8, got 300"),
        ("serial", "stop_bits", "0", "must be 1 or 2"),
        ("serial", "stop_bits", "3", "must be 1 or 2"),
        ("serial", "path", "\"\"", "must not be empty"),
        ("serial", "path", "\"  \"", "must not be empty"),
        (
            "tcp",
            "listen",
            "\"0.0.0.0\"",
            "expected an address like 0.0.0.0:502",
        ),
        (
            "tcp",
            "listen",
            "\"localhost:502\"",
            "expected an address like",
        ),
        ("tcp", "max_connections", "0", "must be between 1 and 4096"),
        (
            "tcp",
            "max_connections",
            "4097",
            "must be between 1 and 4096",
        ),
        ("tcp", "idle_timeout_ms", "-5", "must be 0 (never)"),
        (
            "relay",
            "response_timeout_ms",
            "0",
            "must be between 1 and 600000",
        ),
        (
            "relay",
            "response_timeout_ms",
            "600001",
            "must be between 1 and 600000",
        ),
        ("relay", "frame_gap_ms", "0", "must be between 1 and 60000"),
        (
            "relay",
            "frame_gap_ms",
            "60001",
            "must be between 1 and 60000",
        ),
        ("relay", "max_in_flight", "0", "must be between 1 and 255"),
        ("relay", "max_in_flight", "256", "must be between 1 and 255"),
        (
            "relay",
            "max_pending_per_connection",
            "0",
            "must be between 1 and 1024",
        ),
        (
            "relay",
            "max_pending_per_connection",
            "1025",
            "must be between 1 and 1024",
        ),
        ("relay", "queue_depth", "0", "must be between 1 and 65536"),
        (
            "relay",
            "queue_depth",
            "65537",
            "must be between 1 and 65536",
        ),
        ("relay", "retries", "11", "must be between 0 and 10"),
        ("relay", "retries", "-1", "must be between 0 and 10"),
        (
            "serial",
            "silence_floor_ms",
            "1001",
            "must be \"auto\" or 0 to 1000",
        ),
        (
            "serial",
            "rs485_delay_before_send_ms",
            "-1",
            "must be between 0 and 1000",
        ),
        (
            "relay",
            "broadcast_delay_ms",
            "60001",
            "must be between 0 and 60000",
        ),
        (
            "relay",
            "timeout_guard_ms",
            "60001",
            "must be between 0 and 60000",
        ),
        (
            "relay",
            "probe_timeout_ms",
            "0",
            "must be between 1 and 600000",
        ),
        (
            "relay",
            "unit_backoff_after",
            "0",
            "must be between 1 and 100",
        ),
        (
            "relay",
            "unit_backoff_max_ms",
            "0",
            "must be between 1 and 3600000",
        ),
        (
            "log",
            "level",
            "\"verbose\"",
            "must be one of trace, debug, info, warn, error",
        ),
        ("log", "level", "\"INFO\"", "must be one of"),
    ];
    for (section, key, value, msg) in cases {
        // Put the bad key on line 3, column 13 (after a comment line).
        let pad = " ".repeat(12 - key.len().min(12));
        let text = format!("[{section}]\n# comment\n{pad}{key} = {value}\n");
        let col = pad.len() + key.len() + 4;
        let e = err(&text);
        let want = format!("{F}:3:{col}: {section}.{key}: {msg}");
        assert!(e.starts_with(&want), "{e:?} should start with {want:?}");
    }
}

#[test]
fn range_edges_are_accepted() {
    let text = "[serial]\nbaud_rate = 50\ndata_bits = 7\nstop_bits = 2\n\
                [tcp]\nlisten = \"[::1]:1502\"\nmax_connections = 4096\nidle_timeout_ms = 0\n\
                [relay]\nresponse_timeout_ms = 600000\nframe_gap_ms = 1\nmax_in_flight = 255\n\
                max_pending_per_connection = 1024\nqueue_depth = 65536\nretries = 10\n\
                [log]\nlevel = \"trace\"\n";
    let c = parse(text, F).unwrap();
    assert_eq!(c.lines[0].serial.baud_rate, 50);
    assert_eq!(c.listeners[0].tcp.listen, "[::1]:1502".parse().unwrap());
    assert_eq!(c.lines[0].relay.queue_depth, 65536);
    assert_eq!(c.lines[0].relay.retries, 10);
    assert_eq!(
        parse("[serial]\nbaud_rate = 4000000\n", F).unwrap().lines[0]
            .serial
            .baud_rate,
        4_000_000
    );
}

#[test]
fn contradictory_keys_are_refused_naming_both() {
    // The position is that of the first key's value when the file sets it, else
    // that of the other's; dotted keys and inline tables are found too.
    let cases = [
        (
            "[relay]\nmax_pending_per_connection = 100\n",
            "config/test.toml:2:30: relay.max_pending_per_connection: \
             must not exceed relay.queue_depth (64), got 100: \
             one master could pipeline more than the whole queue holds",
        ),
        (
            "[relay]\nretries = 1\nqueue_depth = 8\n",
            "config/test.toml:3:15: relay.max_pending_per_connection: \
             must not exceed relay.queue_depth (8), got 16",
        ),
        (
            "relay.unit_backoff_ms = 5000\nrelay.unit_backoff_max_ms = 10\n",
            "config/test.toml:1:25: relay.unit_backoff_ms: \
             must not exceed relay.unit_backoff_max_ms (10), got 5000: \
             the first backoff would be longer than the longest",
        ),
        (
            "relay = { unit_backoff_max_ms = 999 }\n",
            "config/test.toml:1:33: relay.unit_backoff_ms: \
             must not exceed relay.unit_backoff_max_ms (999), got 1000",
        ),
    ];
    for (text, want) in cases {
        let e = err(text);
        assert!(e.starts_with(want), "{e:?} should start with {want:?}");
    }
    // Equal is fine.
    let c = parse(
        "[relay]\nmax_pending_per_connection = 64\nunit_backoff_ms = 30000\n",
        F,
    )
    .unwrap();
    assert_eq!(
        c.lines[0].relay.max_pending_per_connection,
        c.lines[0].relay.queue_depth
    );

    // A flag that makes the contradiction is named, with both keys.
    let cases: [(&[&str], &str); 4] = [
        (
            &["--max-pending-per-connection", "100"],
            "--max-pending-per-connection: relay.max_pending_per_connection \
             must not exceed relay.queue_depth (64), got 100",
        ),
        (
            &["--queue-depth", "8"],
            "--queue-depth: relay.max_pending_per_connection \
             must not exceed relay.queue_depth (8), got 16",
        ),
        (
            &["--unit-backoff-max-ms", "10"],
            "--unit-backoff-max-ms: relay.unit_backoff_ms \
             must not exceed relay.unit_backoff_max_ms (10), got 1000",
        ),
        (
            &["--unit-backoff-ms", "5000", "--unit-backoff-max-ms", "10"],
            "--unit-backoff-ms: relay.unit_backoff_ms \
             must not exceed relay.unit_backoff_max_ms (10), got 5000",
        ),
    ];
    for (args, want) in cases {
        let mut cfg = Config::default();
        let e = cli(args).unwrap().apply(&mut cfg).unwrap_err().to_string();
        assert!(e.starts_with(want), "{e:?} should start with {want:?}");
        assert_eq!(cfg, Config::default(), "a failed apply must not change cfg");
    }
    // Flags that move both keys together are fine.
    let mut cfg = Config::default();
    cli(&[
        "--max-pending-per-connection",
        "100",
        "--queue-depth",
        "100",
    ])
    .unwrap()
    .apply(&mut cfg)
    .unwrap();
    assert_eq!(cfg.lines[0].relay.queue_depth, 100);
}

#[test]
fn load_names_file_and_os_error() {
    let e = load(Path::new("/nonexistent/mbgate.toml")).unwrap_err();
    let msg = e.to_string();
    assert!(msg.starts_with("/nonexistent/mbgate.toml: "), "{msg}");
    assert!(msg.contains("No such file or directory"), "{msg}");
    assert!(matches!(e, ConfigError::Read { .. }));
}

#[test]
fn load_reads_file_and_reports_its_name() {
    let dir = std::env::temp_dir().join(format!("mbgate-config-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let good = dir.join("good.toml");
    std::fs::write(&good, "[serial]\npath = \"/dev/ttyAMA0\"\n").unwrap();
    assert_eq!(load(&good).unwrap().lines[0].serial.path, "/dev/ttyAMA0");
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, "[serial]\n\n\n\n\n\nbaud_rate = 10\n").unwrap();
    let msg = load(&bad).unwrap_err().to_string();
    assert_eq!(
        msg,
        format!(
            "{}:7:13: serial.baud_rate: must be between 50 and 4000000, got 10",
            bad.display()
        )
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

fn non_default() -> Config {
    let mut c = Config::default();
    c.lines[0].serial = SerialConfig {
        path: "/dev/serial/by-id/usb-FTDI \"quoted\" \\ name".into(),
        baud_rate: 115_200,
        data_bits: 7,
        parity: Parity::Odd,
        stop_bits: 2,
        // XON/XOFF goes with ASCII only.
        flow_control: FlowControl::Software,
        framing: Framing::Ascii,
        port_kind: PortKind::Wire,
        low_latency: false,
        silence_floor_ms: Floor::Ms(0),
        inter_frame_gap_us: 1_000_000,
        rs485: true,
        rs485_delay_before_send_ms: 2,
        rs485_delay_after_send_ms: 1000,
        echo: true,
        // Not "gpio" with rs485 = true: the two contradict each other (its keys
        // apart from it are set, and `direction_round_trip` sets it).
        direction: Direction::None,
        direction_invert: true,
        direction_gpio_chip: "pinctrl-bcm2711".into(),
        direction_gpio_line: GpioLine::Name("GPIO17 \"DE\"".into()),
        direction_delay_before_us: 1_000_000,
        direction_delay_after_us: 1,
    };
    c.listeners[0].tcp = TcpConfig {
        listen: "[::]:1502".parse().unwrap(),
        max_connections: 4096,
        idle_timeout_ms: 0,
    };
    c.lines[0].relay = RelayConfig {
        response_timeout_ms: 600_000,
        frame_gap_ms: 1,
        max_in_flight: 255,
        max_pending_per_connection: 1,
        queue_depth: 65_536,
        retries: 10,
        retry_writes: true,
        notifications: Notifications::Broadcast,
        device_notifications: true,
        broadcast_delay_ms: 0,
        broadcast_reply: BroadcastReply::Echo,
        unit_backoff: false,
        unit_backoff_after: 100,
        unit_backoff_ms: 1,
        unit_backoff_max_ms: 3_600_000,
        probe_timeout_ms: 1,
        timeout_guard_ms: 60_000,
        coalesce: false,
        cache_ms: 3_600_000,
        request_pause_ms: 60_000,
    };
    c.log = LogConfig {
        level: "trace".into(),
        traffic: true,
    };
    c.metrics = MetricsConfig {
        listen: Some("127.0.0.1:9502".parse().unwrap()),
        web_config: "/etc/mbgate/web.yml".into(),
    };
    c
}

#[test]
fn round_trip() {
    for cfg in [Config::default(), non_default()] {
        let text = to_toml(&cfg);
        assert_eq!(parse(&text, "printed").unwrap(), cfg, "{text}");
    }
}

/// `serial.direction` and its line, by offset and by name, printed and read back.
#[test]
fn direction_round_trip() {
    for line in [GpioLine::Offset(17), GpioLine::Name("GPIO17".into())] {
        let mut cfg = non_default();
        cfg.lines[0].serial.rs485 = false;
        cfg.lines[0].serial.flow_control = FlowControl::None;
        cfg.lines[0].serial.direction = Direction::Gpio;
        cfg.lines[0].serial.direction_gpio_line = line;
        let text = to_toml(&cfg);
        assert_eq!(parse(&text, "printed").unwrap(), cfg, "{text}");
    }
}

#[test]
fn printed_configuration_has_the_sections_in_the_documented_order() {
    let text = to_toml(&Config::default());
    let headers: Vec<&str> = text.lines().filter(|l| l.starts_with('[')).collect();
    assert_eq!(
        headers,
        [
            "[serial]",
            "[tcp]",
            "[relay]",
            "[log]",
            "[metrics]",
            "[capture]",
            "[control]"
        ]
    );
    assert!(text.contains("[serial]\npath = \"/dev/ttyUSB0\"\nbaud_rate = 19200\n"));
    assert!(text.contains("listen = \"0.0.0.0:502\"\n"));
    assert!(text.contains("parity = \"none\"\n"));
}

/// A key's value in `cfg` as typed after its flag.
fn flag_value(key: &Key, cfg: &Config) -> String {
    let table: toml::Table = toml::from_str(&format!("v = {}", (key.get)(cfg))).unwrap();
    match &table["v"] {
        toml::Value::String(s) => s.clone(),
        v => v.to_string(),
    }
}

#[test]
fn overrides_apply_every_field() {
    // One flag a declared key, each given the value `non_default` has.
    let want = non_default();
    let args: Vec<String> = KEYS
        .iter()
        .map(|k| format!("--{}={}", k.flag, flag_value(k, &want)))
        .collect();
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = cli(&args).unwrap();
    let mut cfg = Config::default();
    o.apply(&mut cfg).unwrap();
    assert_eq!(cfg, want);

    // No flags: nothing changes.
    let mut cfg = want.clone();
    Overrides::default().apply(&mut cfg).unwrap();
    assert_eq!(cfg, want);
}

#[test]
fn overrides_validate_and_name_the_flag() {
    // As typed on the command line. (`--log-level` is refused by clap itself, see
    // below; `apply` checks it too for callers that build `Overrides` in code.)
    let cases: [(&[&str], &str); 11] = [
        (
            &["--baud", "10"],
            "--baud: must be between 50 and 4000000, got 10",
        ),
        (&["--data-bits", "9"], "--data-bits: must be 7 or 8, got 9"),
        (&["--stop-bits", "0"], "--stop-bits: must be 1 or 2, got 0"),
        (&["--serial", ""], "--serial: must not be empty"),
        (
            &["--response-timeout-ms", "0"],
            "--response-timeout-ms: must be between 1 and 600000, got 0",
        ),
        (
            &["--frame-gap-ms", "60001"],
            "--frame-gap-ms: must be between 1 and 60000",
        ),
        (
            &["--max-in-flight", "256"],
            "--max-in-flight: must be between 1 and 255",
        ),
        (
            &["--max-pending-per-connection", "0"],
            "--max-pending-per-connection: must be between 1 and 1024",
        ),
        (
            &["--queue-depth", "70000"],
            "--queue-depth: must be between 1 and 65536",
        ),
        (
            &["--max-connections", "0"],
            "--max-connections: must be between 1 and 4096",
        ),
        (&["--retries", "11"], "--retries: must be between 0 and 10"),
    ];
    for (args, want) in cases {
        let mut cfg = Config::default();
        let e = cli(args).unwrap().apply(&mut cfg).unwrap_err().to_string();
        assert!(e.starts_with(want), "{e:?} should start with {want:?}");
        assert_eq!(cfg, Config::default(), "a failed apply must not change cfg");
    }
    let mut level = Overrides::default();
    assert!(level.set("log-level", Raw::Str("loud".into())));
    let e = level.apply(&mut Config::default()).unwrap_err().to_string();
    assert!(e.starts_with("--log-level: must be one of trace, debug, info, warn, error"));
    // A later bad flag leaves earlier good ones unapplied too.
    let mut cfg = Config::default();
    let o = cli(&["--baud", "9600", "--retries", "99"]).unwrap();
    assert!(o.apply(&mut cfg).is_err());
    assert_eq!(cfg, Config::default());
}

#[derive(Parser, Debug)]
struct Cli {
    #[command(flatten)]
    overrides: Overrides,
}

fn cli(args: &[&str]) -> Result<Overrides, clap::Error> {
    Cli::try_parse_from(std::iter::once("mbgate").chain(args.iter().copied())).map(|c| c.overrides)
}

#[test]
fn command_line_flags_parse() {
    let o = cli(&[
        "--serial",
        "/dev/ttyS1",
        "--listen",
        "127.0.0.1:1502",
        "--baud",
        "9600",
        "--data-bits",
        "7",
        "--parity",
        "even",
        "--stop-bits",
        "2",
        "--flow-control",
        "none",
        "--framing",
        "rtu",
        "--rs485",
        "--echo=false",
        "--broadcast-reply",
        "echo",
        "--unit-backoff-after",
        "5",
        "--response-timeout-ms",
        "500",
        "--frame-gap-ms",
        "20",
        "--max-in-flight",
        "2",
        "--max-pending-per-connection",
        "4",
        "--queue-depth",
        "8",
        "--max-connections",
        "3",
        "--idle-timeout-ms",
        "0",
        "--retries",
        "1",
        "--retry-writes",
        "--notifications",
        "broadcast",
        "--log-level",
        "debug",
        "--traffic",
    ])
    .unwrap();
    let mut cfg = Config::default();
    o.apply(&mut cfg).unwrap();
    assert_eq!(cfg.lines[0].serial.path, "/dev/ttyS1");
    assert_eq!(
        cfg.listeners[0].tcp.listen,
        "127.0.0.1:1502".parse().unwrap()
    );
    assert_eq!(cfg.lines[0].serial.parity, Parity::Even);
    assert_eq!(cfg.lines[0].serial.flow_control, FlowControl::None);
    assert_eq!(cfg.lines[0].serial.framing, Framing::Rtu);
    assert_eq!(
        (cfg.lines[0].serial.rs485, cfg.lines[0].serial.echo),
        (true, false)
    );
    assert_eq!(cfg.lines[0].relay.broadcast_reply, BroadcastReply::Echo);
    assert_eq!(cfg.lines[0].relay.unit_backoff_after, 5);
    assert_eq!(cfg.lines[0].relay.notifications, Notifications::Broadcast);
    assert!(cfg.lines[0].relay.retry_writes);
    assert!(cfg.log.traffic);
    assert_eq!(cfg.log.level, "debug");
    assert_eq!(cfg.lines[0].serial.baud_rate, 9600);
    assert_eq!(cfg.lines[0].relay.max_pending_per_connection, 4);
    assert_eq!(cfg.listeners[0].tcp.idle_timeout_ms, 0);

    assert_eq!(cli(&[]).unwrap(), Overrides::default());
    let o = cli(&["--traffic=false", "--retry-writes=false"]).unwrap();
    assert!(o.given("traffic") && o.given("retry-writes"));
    let mut cfg = Config::default();
    cfg.log.traffic = true;
    cfg.lines[0].relay.retry_writes = true;
    o.apply(&mut cfg).unwrap();
    assert_eq!(
        (cfg.log.traffic, cfg.lines[0].relay.retry_writes),
        (false, false)
    );
}

#[test]
fn command_line_rejects_bad_values_naming_the_flag() {
    for (args, flag) in [
        (&["--parity", "mark"][..], "--parity"),
        (&["--listen", "0.0.0.0"][..], "--listen"),
        (&["--baud", "fast"][..], "--baud"),
        (&["--log-level", "loud"][..], "--log-level"),
        (&["--traffic=maybe"][..], "--traffic"),
    ] {
        let e = cli(args).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains(flag), "{msg}");
        assert_eq!(e.exit_code(), 2);
    }
    let msg = cli(&["--listen", "0.0.0.0"]).unwrap_err().to_string();
    assert!(
        msg.contains("expected an address like 0.0.0.0:502"),
        "{msg}"
    );
}

/// docs/configuration.md's table has one row per declared key, with its default as the
/// file writes it; its list of flags names every flag. (config/mbgate.toml is held to
/// the declarations by `shipped_file_is_defaults`.)
#[test]
fn the_reference_table_and_flag_list_follow_the_declarations() {
    let readme = include_str!("../../docs/configuration.md");
    let rows: Vec<(String, String)> = readme
        .lines()
        .filter_map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            let key = cells.get(1)?.strip_prefix('`')?.strip_suffix('`')?;
            let default = cells.get(2)?.strip_prefix('`')?.strip_suffix('`')?;
            key.contains('.')
                .then(|| (key.to_owned(), default.to_owned()))
        })
        .collect();
    let declared: Vec<(String, String)> = KEYS
        .iter()
        .map(|k| {
            let default = (k.get)(&Config::default());
            (format!("{}.{}", k.section, k.name), default)
        })
        .collect();
    assert_eq!(
        rows, declared,
        "docs/configuration.md's table against config::KEYS"
    );
    let flags = &readme[readme.find("Every configuration key has a flag").unwrap()..];
    let flags = &flags[..flags.find("\n\n").unwrap()];
    for key in KEYS {
        let flag = format!("`--{}", key.flag);
        assert!(
            flags.contains(&flag),
            "{flag} missing from docs/configuration.md's list"
        );
    }
}

/// The key names and defaults of a table inside a line or a listener, as declared.
fn declared<C: Default>(keys: &[Key<C>]) -> Vec<(&'static str, String)> {
    for k in keys {
        assert!(
            !k.help.trim().is_empty(),
            "{}.{} has no help",
            k.section,
            k.name
        );
    }
    let defaults = C::default();
    keys.iter().map(|k| (k.name, (k.get)(&defaults))).collect()
}

/// Each table inside a line or a listener has its table in docs/configuration.md,
/// headed `in a ...`: one row per declared key, in their order (a row may name
/// several, `read_only`, `write`), and a default written as code is the declared one.
/// A `[[listen]]`'s rows also name the keys of `[tcp]` it takes.
#[test]
fn the_tables_inside_lines_and_listeners_follow_their_declarations() {
    use mbgate::config::access::*;
    use mbgate::config::master::ROUTE_KEYS;
    let doc = include_str!("../../docs/configuration.md");
    let tcp: Vec<&str> = ["address", "max_connections", "idle_timeout_ms"].to_vec();
    let tables = [
        ("in a `[[line.route]]`", declared(ROUTE_KEYS)),
        ("in a `[[line.unit]]`", declared(UNIT_KEYS)),
        ("in a `[[listen]]`", declared(LISTEN_KEYS)),
        ("in a `[[dial]]`", declared(mbgate::config::dial::DIAL_KEYS)),
        (
            "in a `[[dial]]`'s `tls`",
            declared(mbgate::config::dial::DIAL_TLS_KEYS),
        ),
        ("in a listener's `tls`", declared(LISTEN_TLS_KEYS)),
        ("in a `[[role]]`", declared(ROLE_KEYS)),
        ("in a `write` rule", declared(RULE_KEYS)),
        ("in a `[[line]]`'s `tcp`", declared(LINE_TCP_KEYS)),
        ("in a `[[line]]`'s `tcp.tls`", declared(DEVICE_TLS_KEYS)),
    ];
    for (header, keys) in tables {
        let at = doc
            .find(&format!("| {header} |"))
            .unwrap_or_else(|| panic!("no table `{header}` in docs/configuration.md"));
        let rows = doc[at..].lines().skip(2).take_while(|l| l.starts_with('|'));
        let mut documented = Vec::new();
        for row in rows {
            let cells: Vec<&str> = row.split('|').map(str::trim).collect();
            let default = cells
                .get(2)
                .and_then(|c| c.strip_prefix('`')?.strip_suffix('`'));
            for name in cells[1].split(", ") {
                let name = name.trim_matches('`');
                if header == "in a `[[listen]]`" && tcp.contains(&name) {
                    continue;
                }
                let declared = keys.iter().find(|(k, _)| *k == name);
                let declared =
                    declared.unwrap_or_else(|| panic!("{header}: `{name}` is not declared"));
                if let (Some(doc), true) = (default, cells.len() > 4) {
                    assert_eq!(doc, declared.1, "{header}: the default of `{name}`");
                }
                documented.push(name);
            }
        }
        let names: Vec<&str> = keys.iter().map(|(k, _)| *k).collect();
        assert_eq!(
            documented, names,
            "{header}: docs/configuration.md against the declarations"
        );
    }
}

#[test]
fn every_key_has_its_own_flag_and_help() {
    for (i, key) in KEYS.iter().enumerate() {
        assert!(!key.help.trim().is_empty(), "{} has no help", key.name);
        let same = KEYS[..i].iter().find(|k| k.flag == key.flag);
        assert!(same.is_none(), "--{} is declared twice", key.flag);
    }
}

/// `[[line]]` (its `serial` and `relay` tables) and `[[listen]]` (`address` for
/// `listen`) describe the same one line and one listener as `[serial]`, `[relay]` and
/// `[tcp]` (docs/design.md §4.1).
#[test]
fn the_lines_form_means_the_same() {
    for cfg in [Config::default(), non_default()] {
        let text = to_toml_lines(&cfg);
        assert_eq!(parse(&text, "printed").unwrap(), cfg, "{text}");
    }
    let old = "[serial]\nbaud_rate = 9600\nframing = \"rtu\"\n[relay]\nretries = 2\n\
               [tcp]\nlisten = \"127.0.0.1:1502\"\n[log]\nlevel = \"debug\"\n";
    let new = "[[line]]\nserial = { baud_rate = 9600, framing = \"rtu\" }\n\
               [line.relay]\nretries = 2\n\
               [[listen]]\naddress = \"127.0.0.1:1502\"\n[log]\nlevel = \"debug\"\n";
    assert_eq!(parse(new, F).unwrap(), parse(old, F).unwrap());
    // Either table alone: the other side keeps the old form or its defaults.
    let c = parse(
        "[[listen]]\nmax_connections = 3\n[serial]\nbaud_rate = 9600\n",
        F,
    )
    .unwrap();
    assert_eq!(
        (
            c.listeners[0].tcp.max_connections,
            c.lines[0].serial.baud_rate
        ),
        (3, 9600)
    );
    let printed = to_toml_lines(&Config::default());
    assert!(
        printed.starts_with("[[line]]\n\n[line.serial]\npath = "),
        "{printed}"
    );
    assert!(
        printed.contains("\n[[listen]]\naddress = \"0.0.0.0:502\"\n"),
        "{printed}"
    );
}

/// The new form is checked as closely as the old, at the position of what is wrong.
#[test]
fn lines_and_listeners_are_validated() {
    let cases = [
        (
            "[[line]]\nunits = [\"1-3\"]\n[[line]]\nunits = [3]\n",
            "4:10: line[1].units: unit 3 is also in line[0].units",
        ),
        (
            "[[line]]\nunits = [\"5-3\"]\n",
            "2:10: line[0].units: the range \"5-3\" is empty",
        ),
        (
            "[[line]]\nunits = [\"a-3\"]\n",
            "2:10: line[0].units: expected a unit id or a range like \"10-20\", got \"a-3\"",
        ),
        (
            "[[line]]\nunits = [1]\nremap = { 1 = 2 }\n",
            "3:11: line[0].remap: unit 1 is also in line[0].units",
        ),
        (
            "[[line]]\nremap = { 300 = 2 }\n",
            "2:11: line[0].remap: \"300\" is not a unit id (1 to 255)",
        ),
        (
            "[[line]]\nremap = { 11 = 256 }\n",
            "2:16: line[0].remap: must be between 0 and 255, got 256",
        ),
        (
            "[[line]]\ntcp = { framing = \"rtu\" }\n",
            "2:7: line[0].tcp.address: missing: the device's host:port",
        ),
        (
            "[[line]]\ntcp = { address = \"plc.local\" }\n",
            "2:19: line[0].tcp.address: expected host:port, like 192.168.1.20:502, got \"plc.local\"",
        ),
        (
            "[[line]]\ntcp = { address = \"plc:502\", baud_rate = 9600 }\n",
            "2:30: line[0].tcp.baud_rate: unknown key; expected one of address, framing",
        ),
        (
            "[[line]]\ntcp = { address = \"plc:502\" }\nserial = { path = \"/dev/ttyS0\" }\n",
            "3:1: line[0].serial: a line's device is a serial port or a TCP address",
        ),
        (
            "[[listen]]\nframing = \"ascii\"\n",
            "2:11: listen[0].framing: invalid value \"ascii\"; expected one of mbap, rtu",
        ),
        (
            "[[line]]\nunits = [1]\n[[line]]\n",
            "3:1: line[1].units: missing: with several lines, each says which unit ids it serves",
        ),
        (
            "[[line]]\nunits = [1, 2]\n[[line]]\nunits = [3, 2]\n",
            "4:13: line[1].units: unit 2 is also in line[0].units",
        ),
        (
            "[[line]]\nunits = [1]\nserial = { path = \"/dev/a\" }\n[[line]]\nunits = [2]\nserial = { path = \"/dev/a\" }\n",
            "6:19: line[1].serial.path: the same as line[0]'s (\"/dev/a\"): each line has its own port or address",
        ),
        (
            "[[line]]\nunits = [1]\ntcp = { address = \"plc:502\" }\n[[line]]\nunits = [2]\n[line.tcp]\naddress = \"plc:502\"\n",
            "7:11: line[1].tcp.address: the same as line[0]'s (\"plc:502\"): each line has its own port or address",
        ),
        (
            "[[line]]\nunits = [1, 1]\n",
            "2:13: line[0].units: unit 1 is also in line[0].units",
        ),
        (
            "[[line]]\nunits = [0]\n",
            "2:10: line[0].units: must be between 1 and 255, got 0",
        ),
        (
            "[[line]]\nunits = []\n",
            "2:9: line[0].units: must list at least one unit id",
        ),
        (
            "[[line]]\nunits = 5\n",
            "2:9: line[0].units: invalid type: integer `5`, expected an array of unit ids",
        ),
        (
            "[[line]]\nunit = [1]\n",
            "2:8: line[0].unit: expected [[line.unit]] tables (the unit ids the line serves are its `units`)",
        ),
        (
            "[[line]]\n[line.serial]\nbaudrate = 9600\n",
            "3:1: line[0].serial.baudrate: unknown key; expected one of path, baud_rate,",
        ),
        (
            "[[line]]\n[line.serial]\nbaud_rate = 10\n",
            "3:13: line[0].serial.baud_rate: must be between 50 and 4000000, got 10",
        ),
        (
            "[[line]]\n[line.relay]\nqueue_depth = 4\n",
            "3:15: line[0].relay.max_pending_per_connection: must not exceed \
             line[0].relay.queue_depth (4), got 16",
        ),
        (
            "[[listen]]\nlisten = \"0.0.0.0:502\"\n",
            "2:1: listen[0].listen: unknown key; expected one of address, max_connections, \
             idle_timeout_ms, framing",
        ),
        (
            "[[listen]]\naddress = \"0.0.0.0\"\n",
            "2:11: listen[0].address: expected an address like 0.0.0.0:502, got \"0.0.0.0\"",
        ),
        (
            "[relay]\nretries = 1\n[[line]]\n",
            "3:3: line: [[line]] replaces [relay]: write one form or the other",
        ),
        (
            "[[listen]]\n[tcp]\n",
            "1:3: listen: [[listen]] replaces [tcp]: write one form or the other",
        ),
        ("line = 5\n", "1:8: line: expected [[line]] tables"),
        (
            "line = [5]\n",
            "1:9: line[0]: invalid type: integer `5`, expected a table ([[line]])",
        ),
    ];
    for (text, want) in cases {
        let e = err(text);
        let want = format!("{F}:{want}");
        assert!(
            e.starts_with(&want),
            "{text:?}:\n{e:?}\nshould start with\n{want:?}"
        );
    }
}

/// The example of docs/design.md §4.1 is read as two lines with their units; one
/// line serving every unit is the old form.
#[test]
fn the_documented_example_of_several_lines_is_read_as_written() {
    let doc = include_str!("../../docs/design.md");
    let example = &doc[doc.find("### 4.1").unwrap()..];
    let example = &example[example.find("```toml\n").unwrap() + 8..];
    let example = &example[..example.find("```").unwrap()];
    let cfg = parse(example, "docs/design.md").unwrap();
    let lines = &cfg.lines;
    assert_eq!(lines.len(), 3);
    assert_eq!(
        (lines[0].serial.framing, lines[0].relay.response_timeout_ms),
        (Framing::Rtu, 500)
    );
    assert_eq!(
        lines[0].units.ids.iter().copied().collect::<Vec<_>>(),
        [1, 2, 3]
    );
    assert_eq!(lines[1].units.remap.get(&11), Some(&1));
    assert_eq!(lines[2].tcp.as_deref(), Some("192.168.1.20:502"));
    assert_eq!(cfg.listeners.len(), 2);
    // Printed back, it reads the same.
    assert_eq!(
        parse(&to_toml(&cfg), "printed").unwrap(),
        cfg,
        "{}",
        to_toml(&cfg)
    );
    // With one line and no units, it is the single-line form's one line serving every unit.
    let one = &example[..example.find("[[line]]\nunits = [10").unwrap()];
    let one = one.replace("units = [1, 2, 3]", "");
    let cfg = parse(&one, "docs/design.md").unwrap();
    assert_eq!(cfg.lines.len(), 1);
    assert_eq!(cfg.lines[0].units, Default::default());
    assert_eq!(
        (
            cfg.lines[0].serial.framing,
            cfg.lines[0].relay.response_timeout_ms
        ),
        (Framing::Rtu, 500)
    );
}

/// With several lines a serial or relay flag could mean any of them: refused, naming
/// the flag; the log's flags still apply.
#[test]
fn flags_for_a_line_are_refused_when_the_file_has_several() {
    let text = "[[line]]\nunits = [1]\nserial = { path = \"/dev/a\" }\n\
                [[line]]\nunits = [2]\nserial = { path = \"/dev/b\" }\n";
    let dir = std::env::temp_dir().join(format!("mbgate-flags-lines-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("lines.toml");
    std::fs::write(&file, text).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_mbgate"))
        .args(["check-config", file.to_str().unwrap(), "--baud", "9600"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("--baud: the file describes the gateway as [[line]] tables: set it there"),
        "{err}"
    );
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_mbgate"))
        .args([
            "check-config",
            file.to_str().unwrap(),
            "--print",
            "--log-level",
            "debug",
        ])
        .output()
        .unwrap();
    assert!(out.status.success());
    let printed = String::from_utf8_lossy(&out.stdout);
    assert!(
        printed.starts_with("[[line]]\nunits = [1]\n\n[line.serial]\n"),
        "{printed}"
    );
    assert!(printed.contains("\n[[line]]\nunits = [2]\n"), "{printed}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// One shape whichever form the file is in (docs/architecture.md "One shape of the
/// configuration"): `[serial]`, `[relay]` and `[tcp]` read into the same lines and
/// listeners as the `[[line]]` and `[[listen]]` tables that say the same, and a flag
/// sets the one line's value itself, whichever form it came in; with several lines a
/// flag is refused rather than set on one.
#[test]
fn both_forms_read_into_one_shape_and_the_flags_set_the_line() {
    let single = "[serial]\npath = \"/dev/ttyS2\"\nframing = \"rtu\"\nflow_control = \"none\"\n\
                  [relay]\nresponse_timeout_ms = 300\n[tcp]\nlisten = \"127.0.0.1:1502\"\n";
    let tables = "[[line]]\nserial = { path = \"/dev/ttyS2\", framing = \"rtu\", flow_control = \"none\" }\n\
                  relay = { response_timeout_ms = 300 }\n\
                  [[listen]]\naddress = \"127.0.0.1:1502\"\n";
    let (a, b) = (parse(single, F).unwrap(), parse(tables, F).unwrap());
    assert_eq!(a, b);
    assert_eq!((a.lines.len(), a.listeners.len()), (1, 1));
    assert_eq!(a.lines[0].relay.response_timeout_ms, 300);
    assert_eq!(a.listeners[0].tcp.listen, "127.0.0.1:1502".parse().unwrap());

    let flags = cli(&["--response-timeout-ms", "700", "--listen", "127.0.0.1:1503"]).unwrap();
    for mut cfg in [a, b] {
        flags.apply(&mut cfg).unwrap();
        assert_eq!(cfg.lines[0].relay.response_timeout_ms, 700);
        assert_eq!(
            cfg.listeners[0].tcp.listen,
            "127.0.0.1:1503".parse().unwrap()
        );
        assert_eq!((cfg.lines.len(), cfg.listeners.len()), (1, 1));
    }

    let two = format!("{tables}[[line]]\nunits = [2]\nserial = {{ path = \"/dev/ttyS3\" }}\n")
        .replacen("[[line]]\n", "[[line]]\nunits = [1]\n", 1);
    let mut cfg = parse(&two, F).unwrap();
    let e = flags.apply(&mut cfg).unwrap_err().to_string();
    assert!(e.contains("[[line]] tables"), "{e}");
    assert_eq!(cfg, parse(&two, F).unwrap(), "left as it was");
}

/// A configuration path that names something endless (`/dev/zero`) is refused once it
/// passes the most a configuration holds, with the file named and exit 2, not read
/// until memory runs out (before: 2.8 GB of RSS in 5 s, and on).
#[test]
fn an_endless_file_is_refused_not_read() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_mbgate"))
        .args(["check-config", "/dev/zero"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("/dev/zero: cannot read the configuration file: larger than 1048576 bytes"),
        "{err}"
    );
}

/// `relay.timeout_guard_ms = 0` is refused on an RTU or ASCII line, naming the file,
/// the line, the key and why (a device that drops requests while busy has its late
/// answer kept off the next request by the guard alone), in either form of the file
/// and as a flag; an MBAP line takes it (a late answer is known by its id there)
/// (docs/reliability.md "RTU and ASCII", 3).
#[test]
fn no_guard_is_refused_on_rtu_and_ascii_lines() {
    let why = "a late answer from a device that dropped the next request while busy is \
               kept off that request only by the guard; set 1 or more (100 by default)";
    for framing in ["rtu", "ascii"] {
        let tables = format!(
            "[[line]]\nserial = {{ path = \"/dev/ttyUSB0\", framing = \"{framing}\" }}\n\
             relay = {{ timeout_guard_ms = 0 }}\n"
        );
        let want = format!(
            "{F}:3:30: line[0].relay.timeout_guard_ms: cannot go with \
             line[0].serial.framing = \"{framing}\": {why}"
        );
        assert_eq!(err(&tables), want);
        let single = format!(
            "[serial]\npath = \"/dev/ttyUSB0\"\nframing = \"{framing}\"\n\
             [relay]\ntimeout_guard_ms = 0\n"
        );
        let want = format!(
            "{F}:5:20: relay.timeout_guard_ms: cannot go with serial.framing = \
             \"{framing}\": {why}"
        );
        assert_eq!(err(&single), want);
        let mut cfg = parse(&single.replace("timeout_guard_ms = 0", ""), F).unwrap();
        let flags = cli(&["--timeout-guard-ms", "0"]).unwrap();
        let e = flags.apply(&mut cfg).unwrap_err().to_string();
        assert!(
            e.contains(&format!(
                "--timeout-guard-ms: relay.timeout_guard_ms cannot go with serial.framing = \
                 \"{framing}\""
            )),
            "{e}"
        );
    }
    let mbap =
        "[serial]\npath = \"/dev/ttyUSB0\"\nframing = \"mbap\"\n[relay]\ntimeout_guard_ms = 0\n";
    assert_eq!(parse(mbap, F).unwrap().lines[0].relay.timeout_guard_ms, 0);
}
