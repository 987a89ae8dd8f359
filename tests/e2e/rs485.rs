//! The RS-485 transmitter switched by the gateway (`serial.direction`, docs/rs485.md)
//! against third-party peers: pymodbus' `ModbusSerialServer` as the device on a socat
//! pty pair, Debian's `mbpoll` and a raw MBAP master. A pty has no modem lines, and
//! this machine may have no GPIO chip: what is proven here is the error path (the
//! setting named at open, the port retried like a lost one, masters answered at once,
//! never left hanging); where a GPIO chip is present, a line of it is driven too.

use crate::common;
use common::*;
use std::process::Command;
use std::time::{Duration, Instant};

/// The MBAP exception reply to an FC 03 request, byte for byte (Modbus Application
/// Protocol V1.1b3 §7).
fn exception(tid: u16, unit: u8, function: u8, code: u8) -> Vec<u8> {
    let [hi, lo] = tid.to_be_bytes();
    vec![hi, lo, 0, 0, 0, 3, unit, function | 0x80, code]
}

/// A pymodbus RTU device on a fresh pty pair, and the gateway's configuration for
/// the other end, RTU without flow control.
fn rtu_device(dir: &std::path::Path) -> (Socat, Py, Cfg) {
    let socat = Socat::start(dir);
    let serve = format!("rtu:{}:19200", socat.dev.display());
    let device = Py::start("serial_servers.py", &["--serve", &serve]);
    let cfg = Cfg::new(&socat.gw)
        .serial("framing = \"rtu\"")
        .serial("baud_rate = 19200")
        .serial("flow_control = \"none\"");
    (socat, device, cfg)
}

/// `mbpoll` reading one holding register of unit 1 once: whether it succeeded, and
/// what it printed.
fn mbpoll_read(port: u16) -> (bool, String) {
    let out = Command::new("mbpoll")
        .args(["-m", "tcp", "-p", &port.to_string(), "-a", "1"])
        .args([
            "-0",
            "-1",
            "-o",
            "3",
            "-t",
            "4",
            "-r",
            "0",
            "-c",
            "1",
            "127.0.0.1",
        ])
        .output()
        .expect("mbpoll (apt-get install mbpoll; scripts/test does)");
    let text =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
}

/// The port opens, the switch does not: the error names the setting, the port is
/// retried as a lost one is, and every master gets "gateway path unavailable" at
/// once (docs/design.md: no port, 0x0A at once), never a hang.
fn refused_with(gw: &Gateway, named: &str) {
    gw.wait_log(named, Duration::from_secs(10));
    // Retried with backoff, each attempt refused the same way (at debug level).
    gw.wait_log("serial port still unavailable: ", Duration::from_secs(10));
    let mut m = gw.connect();
    for tid in 1..=3 {
        let start = Instant::now();
        assert_eq!(
            transact(&mut m, &read_req(tid, 1, 0, 1)),
            exception(tid, 1, 3, 0x0A),
            "{}",
            gw.log()
        );
        assert!(start.elapsed() < Duration::from_secs(2), "not at once");
    }
    let (ok, out) = mbpoll_read(gw.addr.port());
    assert!(!ok, "mbpoll read through a line that cannot switch: {out}");
    assert!(
        out.contains("Gateway path unavailable"),
        "mbpoll's own words for 0x0A: {out}"
    );
}

/// `direction = "rts"` on a pty: the pty has no RTS, so the open is refused naming
/// `serial.direction`; with `direction = "none"` the same device answers (so the
/// exceptions come from the switch, not from the device).
#[test]
fn rts_on_a_pty_is_refused_naming_the_setting() {
    let dir = tempdir();
    let (socat, _device, cfg) = rtu_device(dir.path());
    let mut gw = Gateway::start(&cfg.clone().serial("direction = \"rts\""), dir.path());
    let named = format!(
        "serial.direction = \"rts\": {} has no RTS to switch",
        socat.gw.display()
    );
    refused_with(&gw, &named);
    let log = gw.log();
    assert!(log.contains("Inappropriate ioctl for device"), "{log}");
    assert!(
        log.contains("the gateway switches the transmitter by RTS (asserted while sending)"),
        "the start-up log says the method:\n{log}"
    );
    assert!(gw.stop().contains_key("requests"), "clean exit");

    let dir = tempdir();
    let (_socat, _device, cfg) = rtu_device(dir.path());
    let gw = Gateway::start(&cfg, dir.path());
    let mut m = gw.connect();
    let got = transact(&mut m, &read_req(9, 1, 0, 1));
    assert_eq!(&got[..9], &[0, 9, 0, 0, 0, 5, 1, 3, 2], "{}", gw.log());
    let (ok, out) = mbpoll_read(gw.addr.port());
    assert!(ok, "{out}");
}

/// A GPIO chip that is not there, a line past a chip's end or of no such name: each
/// names its setting, and masters get 0x0A at once.
#[test]
fn a_missing_gpio_chip_or_line_is_refused_naming_the_setting() {
    let dir = tempdir();
    let (_socat, _device, cfg) = rtu_device(dir.path());
    let cfg = cfg
        .serial("direction = \"gpio\"")
        .serial("direction_gpio_chip = \"gpiochip97\"")
        .serial("direction_gpio_line = 4");
    let gw = Gateway::start(&cfg, dir.path());
    refused_with(
        &gw,
        "serial.direction_gpio_chip = \"gpiochip97\": no GPIO chip by that path, name or label",
    );
    assert!(
        gw.log()
            .contains("by GPIO line 4 of gpiochip97 (high while sending)"),
        "{}",
        gw.log()
    );

    let dir = tempdir();
    let (_socat, _device, cfg) = rtu_device(dir.path());
    let cfg = cfg
        .serial("direction = \"gpio\"")
        .serial("direction_gpio_line = \"NO_SUCH_LINE_NAME\"");
    let gw = Gateway::start(&cfg, dir.path());
    refused_with(
        &gw,
        "serial.direction_gpio_line = \"NO_SUCH_LINE_NAME\": no line of that name",
    );
}

/// The first GPIO chip of this machine and a line of it nobody uses, if any.
fn free_gpio_line() -> Result<(std::path::PathBuf, u32), String> {
    let chips = gpiocdev::chip::chips().map_err(|e| format!("no GPIO chips: {e}"))?;
    for chip in chips {
        let Ok(c) = gpiocdev::Chip::from_path(&chip) else {
            continue;
        };
        let lines = c.info().map(|i| i.num_lines).unwrap_or(0);
        for offset in 0..lines {
            if c.line_info(offset).is_ok_and(|i| !i.used) {
                return Ok((chip, offset));
            }
        }
    }
    Err("no GPIO chip with a free line on this machine (/dev/gpiochip*)".into())
}

/// Where the machine has a GPIO chip (the emulated Pi's PL061; not this build
/// machine): a line held by another process is refused naming it, then, once
/// released, the gateway takes it (consumer "mbgate", an output) and serves through
/// it; at shutdown it lets it go. Skips, saying why, where there is no chip.
#[test]
fn a_gpio_line_held_elsewhere_is_refused_then_taken() {
    let (chip, offset) = match free_gpio_line() {
        Ok(found) => found,
        Err(why) => {
            eprintln!("SKIPPED a_gpio_line_held_elsewhere_is_refused_then_taken: {why}");
            return;
        }
    };
    let held = gpiocdev::Request::builder()
        .on_chip(&chip)
        .with_consumer("someone-else")
        .with_line(offset)
        .as_output(gpiocdev::line::Value::Inactive)
        .request()
        .expect("request the free line");
    let dir = tempdir();
    let (_socat, _device, cfg) = rtu_device(dir.path());
    let cfg = cfg
        .serial("direction = \"gpio\"")
        .serial(&format!(
            "direction_gpio_chip = {:?}",
            chip.display().to_string()
        ))
        .serial(&format!("direction_gpio_line = {offset}"));
    let mut gw = Gateway::start(&cfg, dir.path());
    refused_with(&gw, "serial.direction_gpio_line: line ");
    assert!(gw.log().contains("\"someone-else\""), "{}", gw.log());
    drop(held);
    let mut m = gw.connect();
    let start = Instant::now();
    loop {
        let got = transact(&mut m, &read_req(7, 1, 0, 1));
        if got[7] == 3 {
            break;
        }
        assert_eq!(got, exception(7, 1, 3, 0x0A));
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "never took the line"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let info = gpiocdev::Chip::from_path(&chip)
        .and_then(|c| c.line_info(offset))
        .unwrap();
    assert!(info.used && info.consumer == "mbgate", "{info:?}");
    assert_eq!(info.direction, gpiocdev::line::Direction::Output);
    gw.stop();
    let info = gpiocdev::Chip::from_path(&chip)
        .and_then(|c| c.line_info(offset))
        .unwrap();
    assert!(!info.used, "released at shutdown: {info:?}");
}
