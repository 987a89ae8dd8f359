//! Logs under journald: when JOURNAL_STREAM names
//! mbgate's stderr, each line is `<N>message fields` with the syslog priority
//! (sd-daemon(3)), no timestamp and no colours, so `journalctl -p warning` shows the
//! warnings; otherwise the usual format is kept.

use crate::common;
use common::*;
use std::io::Read;
use std::time::Duration;

/// Starts a gateway whose serial port is missing (a warning), lets it log, stops it,
/// and returns its log.
fn log_of(launch: Launch) -> String {
    let dir = tempdir();
    let cfg = Cfg::new(&dir.path().join("no-such-tty"));
    let mut gw = Gateway::launch(&cfg, dir.path(), launch);
    gw.wait_log("serial port unavailable", Duration::from_secs(5));
    assert_eq!(gw.terminate(Duration::from_secs(5)).code(), Some(0));
    gw.log()
}

fn line_with<'a>(log: &'a str, needle: &str) -> &'a str {
    log.lines()
        .find(|l| l.contains(needle))
        .unwrap_or_else(|| panic!("no line with {needle:?} in:\n{log}"))
}

#[test]
fn under_journald_each_line_carries_its_priority_and_no_timestamp_or_colour() {
    let log = log_of(Launch::default().journal_stream());
    assert!(!log.contains('\x1b'), "ANSI escapes: {log:?}");
    for line in log.lines() {
        let rest = ["<3>", "<4>", "<6>", "<7>"]
            .iter()
            .find_map(|p| line.strip_prefix(p))
            .unwrap_or_else(|| panic!("no priority prefix: {line:?}"));
        assert!(
            !rest.starts_with(|c: char| c.is_ascii_digit() || c.is_whitespace()),
            "a timestamp or padding after the prefix: {line:?}"
        );
        for level in ["ERROR", "WARN", "INFO", "DEBUG", "TRACE"] {
            assert!(!rest.starts_with(level), "level spelt out: {line:?}");
        }
    }
    // message first, then the fields.
    let listening = line_with(&log, "listening on");
    assert!(
        listening.starts_with("<6>listening on 127.0.0.1:"),
        "{listening}"
    );
    assert!(listening.contains(" serial="), "{listening}");
    let warning = line_with(&log, "serial port unavailable");
    assert!(
        warning.starts_with("<4>serial port unavailable: "),
        "{warning}"
    );
    assert!(warning.contains(" path="), "{warning}");
    assert!(line_with(&log, "SIGTERM received").starts_with("<6>"));
    // The configuration asks for debug: those lines are priority 7.
    assert!(log.lines().any(|l| l.starts_with("<7>")), "{log}");
}

#[test]
fn an_error_at_start_has_the_error_priority() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let launch = Launch::default().journal_stream();
    let (mut cmd, mut stderr) =
        launch.command(["run", "--listen", &addr, "--serial", "/nonexistent/tty"]);
    let mut child = cmd.spawn().expect("start mbgate");
    drop(cmd);
    let mut out = String::new();
    stderr.read_to_string(&mut out).unwrap();
    assert_eq!(child.wait().unwrap().code(), Some(1));
    let line = line_with(&out, "cannot listen on");
    assert!(
        line.starts_with(&format!("<3>mbgate: cannot listen on {addr}")),
        "{out}"
    );
}

#[test]
fn outside_journald_the_usual_format_is_kept() {
    // JOURNAL_STREAM inherited, but stderr is not that stream (e.g. redirected).
    let log = log_of(Launch::default().env("JOURNAL_STREAM", "1:2"));
    assert!(!log.contains("<6>") && !log.contains("<4>"), "{log}");
    let listening = line_with(&log, "listening on");
    assert!(
        listening.starts_with(|c: char| c.is_ascii_digit()),
        "a timestamp first: {listening}"
    );
    assert!(listening.contains(" INFO "), "{listening}");
    assert!(line_with(&log, "serial port unavailable").contains(" WARN "));
    // Not a terminal: no colours either.
    assert!(!log.contains('\x1b'), "{log:?}");
}
