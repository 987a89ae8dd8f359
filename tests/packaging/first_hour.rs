//! End to end: what a new user meets first. The demo's printed commands run as
//! printed, the demo finds a free port when 5020 is taken, and a failed bind says its
//! cause once, with what to do.

use crate::common;

use common::{mbgate, wait_for, Proc, Py};
use std::net::TcpListener;
use std::process::Command;
use std::time::Duration;

/// The command lines in the demo's banner (`what:   COMMAND`).
fn printed_commands(banner: &str) -> Vec<String> {
    banner
        .lines()
        .filter(|l| l.contains(" read --tcp ") || l.contains(" write --tcp "))
        .map(|l| {
            l.split_once(':')
                .expect("label: command")
                .1
                .trim()
                .to_string()
        })
        .collect()
}

/// Runs a printed line as a user would paste it: through a shell, in the directory
/// the demo was started from.
fn paste(line: &str) -> (i32, String) {
    let out = Command::new("sh")
        .arg("-c")
        .arg(line)
        .current_dir(common::repo())
        .output()
        .expect("sh");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("$ {line}\n{text}");
    (out.status.code().unwrap_or(-1), text)
}

#[test]
fn the_demo_prints_commands_that_run_as_printed() {
    let mut d = Proc::start(&["demo", "--listen", "127.0.0.1:0"], "listening on ");
    wait_for("the banner", Duration::from_secs(5), || {
        printed_commands(&d.stdout.lock().unwrap()).len() == 3
    });
    let banner = d.stdout.lock().unwrap().clone();
    let commands = printed_commands(&banner);
    assert!(
        !commands[0].starts_with("mbgate "),
        "mbgate is not on PATH in a test, so the banner names the binary:\n{banner}"
    );
    // Read the inputs, drive outputs 0 and 4, read the outputs back.
    let (code, out) = paste(&commands[0]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("0: "), "{out}");
    let (code, out) = paste(&commands[1]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("wrote 1 register at 8"), "{out}");
    let (code, out) = paste(&commands[2]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("8: 17 (0x0011)"), "{out}");
    // What the profile answers, and the switch to one that answers the usual requests.
    assert!(
        banner.contains("the CIE-M10 manual's register map"),
        "{banner}"
    );
    assert!(banner.contains("exception for anything else"), "{banner}");
    let generic = banner
        .lines()
        .find(|l| l.contains(" demo --profile generic"))
        .unwrap_or_else(|| panic!("no --profile generic in:\n{banner}"));
    assert!(d.terminate(Duration::from_secs(5)).success());
    // That command as printed (another address: 5020 may be taken), then an FC 06
    // write the CIE-M10 profile refuses, answered.
    let args: Vec<&str> = generic.split_whitespace().skip(1).collect();
    let args = [&args[..], &["--listen", "127.0.0.1:0", "--headless"]].concat();
    let mut g = Proc::start(&args, "listening on ");
    wait_for("the banner", Duration::from_secs(5), || {
        printed_commands(&g.stdout.lock().unwrap()).len() == 2
    });
    let read = printed_commands(&g.stdout.lock().unwrap())[0].clone();
    let write = read.replace(" read ", " write ").replace(" 0 10", " 9 3") + " --unit 2";
    let (code, out) = paste(&write);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("9: 3 (0x0003)"), "{out}");
    assert!(g.terminate(Duration::from_secs(5)).success());
}

/// `mbgate demo --lines 2`: a second line with the same device, reached as unit 101;
/// its printed command runs as printed and is answered (the simulated CIE-M10 is unit
/// 1 and stays silent for any other: the gateway remapped it).
#[test]
fn the_demo_with_two_lines_routes_unit_101_to_the_second() {
    let mut d = Proc::start(
        &["demo", "--lines", "2", "--listen", "127.0.0.1:0"],
        "listening on ",
    );
    wait_for("the banner", Duration::from_secs(5), || {
        printed_commands(&d.stdout.lock().unwrap()).len() == 4
    });
    let banner = d.stdout.lock().unwrap().clone();
    let commands = printed_commands(&banner);
    assert!(commands[3].contains("--unit 101"), "{banner}");
    let (code, out) = paste(&commands[3]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("0: "), "{out}");
    let log = d.log();
    assert_eq!(log.matches("serial port open").count(), 2, "{log}");
    assert!(d.terminate(Duration::from_secs(5)).success());
    let log = d.log();
    assert!(log.contains("requests=1 replies=1"), "{log}");
}

#[test]
fn the_demo_takes_a_free_port_when_5020_is_taken() {
    // Whoever holds 5020 (this test, or another program on the machine), the demo must
    // not fail on it.
    let _held = TcpListener::bind("127.0.0.1:5020");
    let mut d = Proc::start(&["demo"], "listening on ");
    let log = d.log();
    let at = log
        .split("listening on ")
        .nth(1)
        .and_then(|r| r.split_whitespace().next())
        .expect("listen address")
        .to_string();
    assert_ne!(at, "127.0.0.1:5020", "{log}");
    wait_for("the banner", Duration::from_secs(5), || {
        d.stdout.lock().unwrap().contains(&at)
    });
    let banner = d.stdout.lock().unwrap().clone();
    assert!(
        banner.contains("another program holds 127.0.0.1:5020; using a free port instead"),
        "{banner}"
    );
    assert!(d.terminate(Duration::from_secs(5)).success());
}

#[test]
fn a_port_in_use_is_said_once_with_what_to_do() {
    let held = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = held.local_addr().unwrap().port();
    let at = format!("127.0.0.1:{port}");
    for args in [
        vec!["run", "--serial", "/nonexistent/tty", "--listen", &at],
        vec!["demo", "--listen", &at],
    ] {
        let out = mbgate(&args);
        assert_eq!(out.code, 1, "{args:?}");
        let cause = "Address already in use";
        assert_eq!(out.stderr.matches(cause).count(), 1, "{}", out.stderr);
        let next = format!("--listen 127.0.0.1:{}", port.wrapping_add(1).max(1024));
        assert!(out.stderr.contains(&next), "{}", out.stderr);
        assert!(
            out.stderr.contains("another process holds port"),
            "{}",
            out.stderr
        );
    }
}

/// A port below 1024 without privilege: the hint names the capability. Run as an
/// unprivileged user when the tests run as root (CI does).
#[test]
fn a_privileged_port_says_how_to_get_it() {
    let unprivileged_from: u16 =
        std::fs::read_to_string("/proc/sys/net/ipv4/ip_unprivileged_port_start")
            .ok()
            .and_then(|s| s.trim().parse().ok())
            .unwrap_or(1024);
    if unprivileged_from <= 502 {
        eprintln!("this kernel lets anyone bind port 502 (ip_unprivileged_port_start = {unprivileged_from}): nothing to check");
        return;
    }
    let bin = env!("CARGO_BIN_EXE_mbgate");
    let args = [
        "run",
        "--serial",
        "/nonexistent/tty",
        "--listen",
        "127.0.0.1:502",
    ];
    let out = if nix_is_root() {
        Command::new("setpriv")
            .args(["--reuid=65534", "--regid=65534", "--clear-groups", bin])
            .args(args)
            .output()
    } else {
        Command::new(bin).args(args).output()
    }
    .expect("run mbgate");
    let stderr = String::from_utf8_lossy(&out.stderr);
    eprintln!("{stderr}");
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert_eq!(stderr.matches("Permission denied").count(), 1, "{stderr}");
    assert!(stderr.contains("CAP_NET_BIND_SERVICE"), "{stderr}");
    assert!(stderr.contains("--listen 127.0.0.1:5020"), "{stderr}");
}

fn nix_is_root() -> bool {
    // SAFETY: getuid has no preconditions and cannot fail.
    unsafe { libc::getuid() == 0 }
}

/// Ctrl-C in the demo's console: what follows starts on a line of its own (not after
/// `sim> `), the counters are shown, and the exit is clean.
#[test]
fn ctrl_c_in_the_demo_console_ends_the_line_and_shows_the_counters() {
    let (status, out) = Py::run("demo_console.py", &[env!("CARGO_BIN_EXE_mbgate")]);
    assert!(status.success(), "demo_console.py:\n{out}");
    let mut lines = out.lines();
    let shown = lines.next().unwrap_or_default();
    assert!(
        shown.starts_with("'\\r\\n") || shown.starts_with("'^C\\r\\n"),
        "the line after the prompt is ended first: {shown}"
    );
    assert!(
        shown.contains("mbgate demo stopped: connections=0"),
        "{shown}"
    );
    assert!(shown.contains("requests=0"), "{shown}");
    assert_eq!(lines.next(), Some("exit 0"), "{out}");
}

/// The register tables have one set of names: docs/read-write.md's table, `read --help`
/// and `write --help` agree on the names and their aliases, and the demo's banner uses
/// them.
#[test]
fn table_names_agree_between_help_and_the_guide() {
    let readme = std::fs::read_to_string(common::repo().join("docs/read-write.md")).unwrap();
    // | `coils` | FC 01 | FC 05, 0F | `coil` |, and for holding registers
    // `holding`, `hr`; for `write` also `registers`, `register`
    let rows: Vec<(String, bool, Vec<String>, Vec<String>)> = readme
        .lines()
        .filter(|l| l.starts_with("| `") && l.contains("| FC 0"))
        .map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            let names = |cell: &str| -> Vec<String> {
                cell.split('`')
                    .skip(1)
                    .step_by(2)
                    .map(str::to_string)
                    .collect()
            };
            let (both, write_only) = cells[4]
                .split_once("; for `write` also")
                .unwrap_or((cells[4], ""));
            (
                names(cells[1])[0].clone(),
                cells[3] != "read-only",
                names(both),
                names(write_only),
            )
        })
        .collect();
    assert_eq!(rows.len(), 4, "docs/read-write.md's table of tables");
    let read = mbgate(&["read", "--help"]).stdout;
    let write = mbgate(&["write", "--help"]).stdout;
    for (name, writable, aliases, write_aliases) in &rows {
        let line = |help: &str| {
            help.lines()
                .find(|l| l.trim_start().starts_with(&format!("- {name}:")))
                .map(str::to_string)
        };
        let r = line(&read).unwrap_or_else(|| panic!("read --help lacks {name}:\n{read}"));
        for alias in aliases {
            assert!(
                r.contains(alias.as_str()),
                "read --help, {name}: {alias}: {r}"
            );
        }
        match line(&write) {
            Some(w) => {
                assert!(writable, "write --help offers read-only {name}");
                for alias in aliases.iter().chain(write_aliases) {
                    assert!(
                        w.contains(alias.as_str()),
                        "write --help, {name}: {alias}: {w}"
                    );
                }
            }
            None => assert!(!writable, "write --help lacks {name}:\n{write}"),
        }
    }
    // The demo's banner names tables the same way (checked where it prints them).
    let banner = std::fs::read_to_string(common::repo().join("src/tools/demo/mod.rs")).unwrap();
    for used in ["holding-registers", "coils"] {
        assert!(
            banner.contains(&format!(" {used} ")),
            "{used} in the banner"
        );
    }
}

/// `mbgate status` with no metrics listener to ask: exit 3, and it says how to turn
/// the listener on (the `[metrics]` lines for that address, the flag, the reload).
#[test]
fn status_without_a_metrics_listener_says_how_to_turn_it_on() {
    let free = TcpListener::bind("127.0.0.1:0").unwrap();
    let at = free.local_addr().unwrap().to_string();
    drop(free);
    let out = mbgate(&["status", "--metrics", &at]);
    assert_eq!(out.code, 3, "{}", out.stderr);
    assert!(
        out.stderr
            .contains(&format!("[metrics]\n    listen = \"{at}\"")),
        "{}",
        out.stderr
    );
    assert!(
        out.stderr.contains(&format!("--metrics-listen {at}")),
        "{}",
        out.stderr
    );
    assert!(out.stderr.contains("systemctl reload"), "{}", out.stderr);
}
