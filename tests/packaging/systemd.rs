//! The shipped units: `systemd-analyze security
//! --offline=true` rates each at an exposure of 1.5 or less, `systemd-analyze verify`
//! has nothing to say about them, the template differs from the single unit only where
//! it must, and the stop timeout covers the default drain.
//!
//! Needs `systemd-analyze` (Debian package systemd). Without it these tests print why
//! and pass, except in CI (`CI` set), where they fail: CI must run them.

use crate::common;
use common::*;
use std::path::PathBuf;
use std::process::{Command, Output};

const UNITS: [&str; 2] = ["mbgate.service", "mbgate@.service"];

/// The highest exposure the issue allows.
const MAX_EXPOSURE: f64 = 1.5;

fn unit_path(name: &str) -> PathBuf {
    repo().join("systemd").join(name)
}

fn unit_text(name: &str) -> String {
    std::fs::read_to_string(unit_path(name)).expect("read unit")
}

fn systemd_analyze(args: &[&str]) -> Option<Output> {
    match Command::new("systemd-analyze").args(args).output() {
        Ok(o) => Some(o),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            assert!(!peer("systemd-analyze", "systemd"));
            None
        }
        Err(e) => panic!("systemd-analyze: {e}"),
    }
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// `→ Overall exposure level for mbgate.service: 1.5 OK 🙂` → 1.5
fn overall_exposure(report: &str) -> Option<f64> {
    let line = report
        .lines()
        .find(|l| l.contains("Overall exposure level"))?;
    line.rsplit(": ")
        .next()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

#[test]
fn exposure_of_each_unit_is_at_most_1_5() {
    for name in UNITS {
        let path = unit_path(name);
        let Some(o) = systemd_analyze(&[
            "security",
            "--offline=true",
            "--threshold=15",
            path.to_str().unwrap(),
        ]) else {
            return;
        };
        let report = text(&o);
        let exposure = overall_exposure(&report)
            .unwrap_or_else(|| panic!("{name}: no overall exposure in:\n{report}"));
        println!("{name}: exposure {exposure}");
        assert!(
            exposure <= MAX_EXPOSURE && o.status.success(),
            "{name}: exposure {exposure} > {MAX_EXPOSURE}:\n{report}"
        );
    }
}

#[test]
fn verify_is_clean() {
    // verify wants ExecStart's binary to exist: check copies that run the one just
    // built instead of /usr/bin/mbgate (where the .deb puts it).
    let dir = tempdir();
    for name in UNITS {
        let text = unit_text(name);
        assert!(text.contains("ExecStart=/usr/bin/mbgate run "), "{name}");
        let text = text.replace("/usr/bin/mbgate", env!("CARGO_BIN_EXE_mbgate"));
        std::fs::write(dir.path().join(name), text).unwrap();
    }
    // The template is checked through an instance, as systemd would load it.
    let single = dir.path().join("mbgate.service");
    let instance = dir.path().join("mbgate@ttyUSB0.service");
    let Some(o) = systemd_analyze(&[
        "verify",
        "--man=no",
        "--generators=no",
        single.to_str().unwrap(),
        instance.to_str().unwrap(),
    ]) else {
        return;
    };
    let said = text(&o);
    assert!(
        o.status.success() && said.trim().is_empty(),
        "systemd-analyze verify: {:?}\n{said}",
        o.status
    );
}

/// A unit's settings, comments and blank lines left out.
fn settings(name: &str) -> Vec<String> {
    unit_text(name)
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(String::from)
        .collect()
}

#[test]
fn the_template_is_the_single_unit_but_for_its_name_and_file() {
    let single = settings("mbgate.service");
    let template = settings("mbgate@.service");
    let differ: Vec<(&String, &String)> = single
        .iter()
        .zip(&template)
        .filter(|(a, b)| a != b)
        .collect();
    assert_eq!(single.len(), template.len(), "{single:#?}\n{template:#?}");
    assert_eq!(
        differ,
        [
            (
                &"Description=mbgate Modbus/TCP to serial gateway".to_string(),
                &"Description=mbgate Modbus/TCP to serial gateway (%I)".to_string()
            ),
            (
                &"ExecStart=/usr/bin/mbgate run --config /etc/mbgate/mbgate.toml".to_string(),
                &"ExecStart=/usr/bin/mbgate run --config /etc/mbgate/%i.toml".to_string()
            ),
        ]
    );
}

/// The value of `key=` in a unit (the last one, as systemd reads it).
fn setting(lines: &[String], key: &str) -> Option<String> {
    lines
        .iter()
        .rev()
        .find_map(|l| l.strip_prefix(&format!("{key}=")))
        .map(String::from)
}

#[test]
fn the_service_contract_is_kept() {
    let s = settings("mbgate.service");
    for (key, want) in [
        ("Type", "notify"),
        ("Restart", "on-failure"),
        ("RestartPreventExitStatus", "2"),
        ("DynamicUser", "yes"),
        ("SupplementaryGroups", "dialout gpio"),
        ("AmbientCapabilities", "CAP_NET_BIND_SERVICE"),
        ("CapabilityBoundingSet", "CAP_NET_BIND_SERVICE"),
        ("DevicePolicy", "closed"),
        ("RestrictAddressFamilies", "AF_INET AF_INET6 AF_UNIX"),
    ] {
        assert_eq!(setting(&s, key).as_deref(), Some(want), "{key}");
    }
    assert!(setting(&s, "WatchdogSec").is_some(), "the watchdog is on");
    // ttyUSB and ttyACM by their majors too: a name is looked up when the unit starts,
    // and matches nothing before the adapter's driver is loaded.
    for dev in [
        "ttyUSB", "ttyACM", "188", "166", "ttyAMA", "ttyS", "gpiochip",
    ] {
        let line = format!("DeviceAllow=char-{dev} rw");
        assert!(s.contains(&line), "{line}");
    }
    // The configuration stays readable: nothing hides /etc.
    for key in ["InaccessiblePaths", "TemporaryFileSystem", "RootDirectory"] {
        assert!(setting(&s, key).is_none(), "{key}");
    }
}

#[test]
fn stop_timeout_covers_the_default_drain() {
    let s = settings("mbgate.service");
    let secs: u64 = setting(&s, "TimeoutStopSec")
        .expect("TimeoutStopSec")
        .parse()
        .expect("TimeoutStopSec in plain seconds");
    // The gateway's own bound (src/gateway/mod.rs): answer_within() + 2 s, and a second
    // to exit; longer configurations extend it with EXTEND_TIMEOUT_USEC.
    let drain = mbgate::config::RelayConfig::default()
        .answer_within()
        .as_secs()
        + 2
        + 1;
    assert!(secs >= drain, "TimeoutStopSec={secs} < {drain}");
}

#[test]
fn exposure_is_read_from_the_report() {
    let report = "✓ UMask= ...\n\n→ Overall exposure level for mbgate.service: 1.5 OK 🙂\n";
    assert_eq!(overall_exposure(report), Some(1.5));
    assert_eq!(overall_exposure("nothing"), None);
}
