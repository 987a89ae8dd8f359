//! The command line (design.md §3): `check-config`, flags over the file, exit code 2 with
//! a message naming the file, line and key.

mod common;
use common::*;

#[test]
fn check_config_prints_the_effective_configuration() {
    let example = repo().join("config/mbgate.toml");
    let o = mbgate(&["check-config", example.to_str().unwrap()]);
    assert!((o.code == 0), "{}", o.stderr);
    let printed = o.stdout;
    let cfg = mbgate::config::parse(&printed, "stdout").expect("output parses back");
    assert_eq!(cfg, mbgate::config::Config::default());
    assert!(printed.contains("[serial]\npath = \"/dev/ttyUSB0\"\nbaud_rate = 19200\n"));

    // Flags override the file.
    let o = mbgate(&[
        "check-config",
        example.to_str().unwrap(),
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
    assert_eq!(cfg.serial.baud_rate, 9600);
    assert_eq!(cfg.serial.path, "/dev/ttyAMA0");
    assert_eq!(
        cfg.relay.notifications,
        mbgate::config::Notifications::Broadcast
    );
    assert_eq!(cfg.relay.max_in_flight, 4);
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
