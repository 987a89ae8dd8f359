//! The command line (docs/design.md §3): `check-config`, flags over the file, exit code 2 with
//! a message naming the file, line and key.

use crate::common;
use common::*;
use std::time::Duration;

#[test]
fn check_config_prints_the_effective_configuration() {
    let example = repo().join("config/mbgate.toml");
    let o = mbgate(&["check-config", example.to_str().unwrap(), "--print"]);
    assert!((o.code == 0), "{}", o.stderr);
    let printed = o.stdout;
    let cfg = mbgate::config::parse(&printed, "stdout").expect("output parses back");
    assert_eq!(cfg, mbgate::config::Config::default());
    assert!(printed.contains("[serial]\npath = \"/dev/ttyUSB0\"\nbaud_rate = 19200\n"));

    // Flags override the file.
    let o = mbgate(&[
        "check-config",
        example.to_str().unwrap(),
        "--print",
        "--baud",
        "9600",
        "--serial",
        "/dev/ttyAMA0",
        "--notifications",
        "broadcast",
        "--max-in-flight",
        "4",
    ]);
    assert!((o.code == 0), "{}", o.stderr);
    let cfg = mbgate::config::parse(&o.stdout, "stdout").unwrap();
    assert_eq!(cfg.lines[0].serial.baud_rate, 9600);
    assert_eq!(cfg.lines[0].serial.path, "/dev/ttyAMA0");
    assert_eq!(
        cfg.lines[0].relay.notifications,
        mbgate::config::Notifications::Broadcast
    );
    assert_eq!(cfg.lines[0].relay.max_in_flight, 4);
}

#[test]
fn bad_configuration_exits_2_naming_file_line_and_key() {
    let dir = tempdir();
    let cases = [
        (
            "[serial]\npath = \"/dev/ttyUSB0\"\nbaudrate = 9600\n",
            ":3:1: serial.baudrate: unknown key",
        ),
        (
            "[relay]\n\nmax_in_flight = 0\n",
            ":3:17: relay.max_in_flight: must be between 1 and 255",
        ),
        (
            "[serial]\nparity = \"mark\"\n",
            ":2:10: serial.parity: invalid value \"mark\"",
        ),
        (
            "[tcp]\nlisten = \"somewhere\"\n",
            ":2:10: tcp.listen: expected an address like 0.0.0.0:502",
        ),
        ("[modbus]\nunit = 1\n", ":1:2: modbus: unknown key"),
        // Every line a master line: no listener is bound, so none may be written.
        (
            "[[line]]\nrole = \"master\"\n[[line.route]]\naddress = \"h:1\"\n\
             [[listen]]\naddress = \"127.0.0.1:5502\"\n",
            ":5:1: listen[0]: every line is a master line (role = \"master\"): no line has a device for Modbus/TCP masters to reach, so mbgate listens for none; remove [[listen]]",
        ),
        (
            "[[line]]\nrole = \"master\"\n[[line.route]]\naddress = \"h:1\"\n[tcp]\nlisten = \"127.0.0.1:5502\"\n",
            ":5:2: tcp: every line is a master line (role = \"master\"): no line has a device for Modbus/TCP masters to reach, so mbgate listens for none; remove [tcp]",
        ),
        // A relay key a master line does not use.
        (
            "[[line]]\nrole = \"master\"\nrelay = { response_timeout_ms = 300 }\n[[line.route]]\naddress = \"h:1\"\n",
            ":3:33: line[0].relay.response_timeout_ms: means nothing on a master line",
        ),
        ("[serial\n", ":1:8: TOML syntax error"),
    ];
    for (i, (text, want)) in cases.iter().enumerate() {
        let file = dir.path().join(format!("bad{i}.toml"));
        std::fs::write(&file, text).unwrap();
        let path = file.to_str().unwrap();
        for cmd in [&["check-config", path][..], &["run", "--config", path][..]] {
            let o = mbgate(cmd);
            assert_eq!(Some(o.code), Some(2), "{cmd:?}: {}", o.stderr);
            let msg = o.stderr;
            assert!(
                msg.contains(&format!("{path}{want}")),
                "{cmd:?}: expected {path}{want} in: {msg}"
            );
        }
    }
}

#[test]
fn unreadable_file_and_bad_flags_exit_2() {
    let o = mbgate(&["run", "--config", "/nonexistent/mbgate.toml"]);
    assert_eq!(Some(o.code), Some(2));
    assert!(o.stderr.contains("/nonexistent/mbgate.toml: cannot read"));

    let o = mbgate(&["run", "--baud", "10"]);
    assert_eq!(Some(o.code), Some(2));
    assert!(o
        .stderr
        .contains("--baud: must be between 50 and 4000000, got 10"));

    let o = mbgate(&["run", "--listen", "nowhere"]);
    assert_eq!(Some(o.code), Some(2));
    assert!(o.stderr.contains("expected an address like 0.0.0.0:502"));

    let o = mbgate(&["run", "--no-such-flag"]);
    assert_eq!(Some(o.code), Some(2));
}

#[test]
fn a_listen_address_in_use_is_a_clear_runtime_error() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let o = mbgate(&["run", "--listen", &addr, "--serial", "/nonexistent/tty"]);
    assert_eq!(Some(o.code), Some(1));
    assert!(
        o.stderr.contains(&format!("cannot listen on {addr}")),
        "{}",
        o.stderr
    );
}

/// `run --help` shows, for every flag, its key and its default.
#[test]
fn run_help_shows_each_flag_s_key_and_default() {
    let o = mbgate(&["run", "--help"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    // Each flag's block starts on a line of its own, indented six spaces.
    let blocks: Vec<String> = o
        .stdout
        .split("\n      --")
        .map(|b| b.split_whitespace().collect::<Vec<_>>().join(" "))
        .collect();
    for key in mbgate::config::KEYS {
        let default = (key.get)(&mbgate::config::Config::default());
        let (flag, section, name) = (key.flag, key.section, key.name);
        let block = blocks
            .iter()
            .find(|b| b.starts_with(&format!("{flag} ")) || b.starts_with(&format!("{flag}[=")))
            .unwrap_or_else(|| panic!("--{flag} missing from:\n{}", o.stdout));
        let shown = format!(
            "[{section}.{name}] [default: {}]",
            default.trim_matches('"')
        );
        assert!(block.contains(&shown), "--{block}\nshould show {shown}");
    }
    let top = mbgate(&["--help"]).stdout;
    for device in ["MBAP", "RTU", "ASCII", "CIE-M10"] {
        assert!(
            top.contains(device),
            "mbgate --help should name {device}: {top}"
        );
        assert!(env!("CARGO_PKG_DESCRIPTION").contains(device));
    }
}

/// `check-config` says on stderr what `run` would warn about at start, word for word,
/// and still exits 0; `--lines` prints the `[[line]]`/`[[listen]]` form.
#[test]
fn check_config_warns_as_run_does() {
    let dir = tempdir();
    let file = dir.path().join("rtu.toml");
    let text = "[serial]\npath = \"/nonexistent/tty\"\nframing = \"rtu\"\n\
                [tcp]\nlisten = \"127.0.0.1:0\"\n\
                [relay]\nmax_in_flight = 4\nnotifications = \"broadcast\"\n";
    std::fs::write(&file, text).unwrap();
    let path = file.to_str().unwrap();
    let checked = mbgate(&["check-config", path]);
    assert_eq!(checked.code, 0, "{}", checked.stderr);
    let warnings: Vec<&str> = checked.stderr.lines().collect();
    // max_in_flight, notifications, and RTS/CTS flow control (the default) on RTU.
    assert_eq!(warnings.len(), 3, "{}", checked.stderr);
    let mut run = Proc::start(&["run", "--config", path], "listening on");
    run.terminate(Duration::from_secs(5));
    for warning in warnings {
        let said = warning.strip_prefix("mbgate: warning: ").unwrap();
        assert!(said.contains("framing = rtu"), "{said}");
        assert!(
            run.log().contains(said),
            "run should say {said:?}:\n{}",
            run.log()
        );
    }
    // An MBAP line has nothing to warn about.
    let quiet = mbgate(&["check-config", path, "--framing", "mbap"]);
    assert_eq!((quiet.code, quiet.stderr.as_str()), (0, ""));

    let lines = mbgate(&["check-config", path, "--lines"]);
    assert_eq!(lines.code, 0, "{}", lines.stderr);
    assert!(lines.stdout.starts_with("[[line]]\n"), "{}", lines.stdout);
    assert!(lines
        .stdout
        .contains("[[listen]]\naddress = \"127.0.0.1:0\"\n"));
    assert_eq!(
        mbgate::config::parse(&lines.stdout, "stdout").unwrap(),
        mbgate::config::load(&file).unwrap()
    );
}

/// A valid file: "OK", then the effective setup a line each (lines with their framing
/// and port settings, listeners with the masters they take, the metrics listener);
/// the whole configuration only with --print.
#[test]
fn check_config_says_ok_and_the_setup_in_a_few_lines() {
    let dir = tempdir();
    let file = dir.path().join("bus.toml");
    std::fs::write(
        &file,
        "[serial]\npath = \"/dev/ttyUSB1\"\nframing = \"rtu\"\nbaud_rate = 9600\n\
         parity = \"even\"\nflow_control = \"none\"\n[metrics]\nlisten = \"127.0.0.1:9502\"\n",
    )
    .unwrap();
    let path = file.to_str().unwrap();
    let o = mbgate(&["check-config", path]);
    assert_eq!((o.code, o.stderr.as_str()), (0, ""));
    assert_eq!(
        o.stdout,
        format!(
            "OK: {path}\n\
             line /dev/ttyUSB1: RTU, 9600 baud 8E1, no flow control, every unit\n\
             listening on 0.0.0.0:502 for Modbus/TCP masters, at most 32 at once\n\
             \x20 # who: from everyone (no allow list), plain TCP\n\
             \x20 # what: read and write\n\
             status page on http://127.0.0.1:9502/, metrics on http://127.0.0.1:9502/metrics \
             (mbgate status --metrics 127.0.0.1:9502)\n"
        )
    );
}

/// A `[control] socket` whose directory does not exist is a bad configuration (exit 2),
/// named by file, line and key: the gateway could not make the socket, and capture and
/// reload would be unavailable. An existing directory is fine.
#[test]
fn check_config_refuses_a_control_socket_in_a_missing_directory() {
    let dir = tempdir();
    let file = dir.path().join("c.toml");
    std::fs::write(
        &file,
        "[serial]\npath = \"/dev/ttyUSB0\"\nflow_control = \"none\"\n\n[control]\nsocket = \"/nonexistent-mbgate/control.sock\"\n",
    )
    .unwrap();
    let path = file.to_str().unwrap();
    let o = mbgate(&["check-config", path]);
    assert_eq!(o.code, 2, "{o:?}");
    assert!(
        o.stderr.starts_with(&format!(
            "mbgate: {path}:6:10: control.socket: the directory /nonexistent-mbgate does not exist"
        )),
        "{}",
        o.stderr
    );
    let sock = dir.path().join("control.sock");
    std::fs::write(
        &file,
        format!("[serial]\npath = \"/dev/ttyUSB0\"\nflow_control = \"none\"\n\n[control]\nsocket = {:?}\n", sock.display().to_string()),
    )
    .unwrap();
    let o = mbgate(&["check-config", path]);
    assert_eq!((o.code, o.stderr.as_str()), (0, ""), "{o:?}");
}

/// The check-config messages a new user met: a host name in `listen` says to give an
/// address; a serial key at the top of the file says which table it belongs in (in
/// either form of the file); `metrics.listen`'s example is the metrics port, not 502;
/// RTU with RTS/CTS flow control (the default) is warned about.
#[test]
fn check_config_says_what_to_write_instead() {
    let dir = tempdir();
    let check = |text: &str| {
        let file = dir.path().join("c.toml");
        std::fs::write(&file, text).unwrap();
        mbgate(&["check-config", file.to_str().unwrap()])
    };
    let o = check("[tcp]\nlisten = \"localhost:502\"\n");
    assert_eq!(o.code, 2);
    assert!(
        o.stderr.contains(
            "tcp.listen: expected an address like 0.0.0.0:502, got \"localhost:502\": a host \
             name is not looked up here; give an IP address of this machine"
        ),
        "{}",
        o.stderr
    );
    let o = check("baud_rate = 9600\n");
    assert_eq!(o.code, 2);
    assert!(
        o.stderr.contains(":1:1: baud_rate: unknown key")
            && o.stderr.contains(
                "did you mean `baud_rate` under [serial], or under [line.serial] in the \
                 [[line]] form?"
            ),
        "{}",
        o.stderr
    );
    let o = check("[[line]]\nbaud_rate = 9600\n");
    assert!(
        o.stderr.contains(
            "line[0].baud_rate: unknown key; expected one of units, remap, serial, tcp, \
             relay, role, route, unit (did you mean `baud_rate` in this line's serial table: under \
             [line.serial], or serial = { baud_rate = ... }?)"
        ),
        "{}",
        o.stderr
    );
    let o = check("[metrics]\nlisten = \"9502\"\n");
    assert_eq!(o.code, 2);
    assert!(
        o.stderr
            .contains("metrics.listen: expected an address like 127.0.0.1:9502, got \"9502\""),
        "{}",
        o.stderr
    );
    let o = check("[serial]\nframing = \"rtu\"\n");
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(
        o.stderr.starts_with(
            "mbgate: warning: framing = rtu with flow_control = hardware (the default"
        ) && o.stderr.contains("set flow_control = \"none\""),
        "{}",
        o.stderr
    );
    let quiet = check("[serial]\nframing = \"rtu\"\nflow_control = \"none\"\n");
    assert_eq!((quiet.code, quiet.stderr.as_str()), (0, ""));
}

/// At start the log names each line with its own framing and settings, then each
/// listener with the masters it takes: an RTU line behind a Modbus/TCP listener no
/// longer reads as an MBAP line.
#[test]
fn the_log_says_each_lines_framing_apart_from_the_listeners() {
    let mut run = Proc::start(
        &[
            "run",
            "--serial",
            "/nonexistent/tty",
            "--framing",
            "rtu",
            "--flow-control",
            "none",
            "--listen",
            "127.0.0.1:0",
        ],
        "listening on",
    );
    run.terminate(Duration::from_secs(5));
    let log = run.log();
    assert!(
        log.contains("line /nonexistent/tty: RTU, 19200 baud 8N1, no flow control, every unit"),
        "{log}"
    );
    let listening = log
        .lines()
        .find(|l| l.contains("listening on"))
        .expect("a listening line");
    assert!(
        listening.contains(" for Modbus/TCP masters") && !listening.contains("framing"),
        "{listening}"
    );
}
