//! The master line's configuration (docs/design.md §4.2): `role = "master"` and
//! `[[line.route]]` tables, read, refused with file, line, column and key, and printed
//! back by `check-config` to the same configuration.

use mbgate::config::master::{MasterLine, Peer, Route};
use mbgate::config::*;

const F: &str = "m.toml";

const EXAMPLE: &str = r#"
[[line]]
role = "master"
serial = { path = "/dev/ttyS1", framing = "rtu", baud_rate = 9600 }

[[line.route]]
units = [1, 2]
address = "plc.local:502"
max_in_flight = 4

[[line.route]]
listen = "127.0.0.1:5021"
response_timeout_ms = 250
"#;

#[test]
fn the_example_reads_and_prints_back_the_same() {
    let cfg = parse(EXAMPLE, F).unwrap();
    assert_eq!(cfg.lines[0].serial.path, "/dev/ttyS1");
    assert_eq!(cfg.lines[0].serial.framing, Framing::Rtu);
    let want = MasterLine {
        routes: vec![
            Route {
                units: vec![1, 2],
                peer: Peer::Connect("plc.local:502".into()),
                response_timeout_ms: 1000,
                max_in_flight: 4,
                allow: None,
            },
            Route {
                units: vec![],
                peer: Peer::Listen("127.0.0.1:5021".parse().unwrap()),
                response_timeout_ms: 250,
                max_in_flight: 1,
                allow: None,
            },
        ],
    };
    assert_eq!(cfg.lines[0].master.as_ref(), Some(&want));
    assert_eq!(want.route_for(2), Some(0));
    assert_eq!(want.route_for(7), Some(1));
    let printed = to_toml(&cfg);
    assert!(
        printed.starts_with("[[line]]\nrole = \"master\"\n"),
        "{printed}"
    );
    assert_eq!(parse(&printed, F).unwrap(), cfg, "{printed}");
    // A slave line (the default role) has no master part.
    let slave = parse("[[line]]\nrole = \"slave\"\n", F).unwrap();
    assert_eq!(slave, Config::default());
}

#[test]
fn mistakes_are_refused_naming_the_key() {
    let line = "[[line]]\nrole = \"master\"\n";
    let route = |body: &str| format!("{line}[[line.route]]\n{body}\n");
    for (text, want) in [
        (
            "[[line]]\nrole = \"boss\"\n".to_owned(),
            "2:8: line[0].role: invalid value \"boss\"; expected one of slave, master",
        ),
        (
            line.to_owned(),
            "2:1: line[0].role: a master line needs [[line.route]] tables",
        ),
        (
            "[[line]]\n[[line.route]]\naddress = \"h:1\"\n".to_owned(),
            "2:8: line[0].route: routes belong to a master line: add role = \"master\"",
        ),
        (
            route("units = [1]"),
            "3:1: line[0].route[0]: missing: address (host:port of the slave) or listen",
        ),
        (
            route("address = \"plc\""),
            "4:11: line[0].route[0].address: expected host:port",
        ),
        (
            route("listen = \"\""),
            "4:10: line[0].route[0].listen: must not be empty (the address where mbgate listens for the slave)",
        ),
        (
            route("address = \"h:1\"\nlisten = \"0.0.0.0:5021\""),
            "5:10: line[0].route[0].listen: give address (connect) or listen, not both",
        ),
        (
            route("units = [0]\naddress = \"h:1\""),
            "4:10: line[0].route[0].units: must be between 1 and 255, got 0",
        ),
        (
            route("units = [1, 1]\naddress = \"h:1\""),
            "4:13: line[0].route[0].units: unit 1 is listed twice",
        ),
        (
            route(
                "units = [1]\naddress = \"h:1\"\n[[line.route]]\nunits = [2, 1]\naddress = \"h:2\"",
            ),
            "7:9: line[0].route[1].units: unit 1 is also in line[0].route[0]",
        ),
        (
            route("address = \"h:1\"\n[[line.route]]\naddress = \"h:2\""),
            "5:1: line[0].route[1]: a second default route (no units); line[0].route[0] is one",
        ),
        (
            route("address = \"h:1\"\nmax_in_flight = 0"),
            "5:17: line[0].route[0].max_in_flight: must be between 1 and 255, got 0",
        ),
        (
            route("adress = \"h:1\""),
            "4:1: line[0].route[0].adress: unknown key; expected one of units, address, listen",
        ),
        (
            format!("{line}relay = {{ retries = 2 }}\n[[line.route]]\naddress = \"h:1\"\n"),
            "3:21: line[0].relay.retries: means nothing on a master line",
        ),
        (
            format!("{line}[line.relay]\nframe_gap_ms = 20\nmax_in_flight = 2\n[[line.route]]\naddress = \"h:1\"\n"),
            "5:17: line[0].relay.max_in_flight: means nothing on a master line (the device is the master: no request of a Modbus/TCP master is queued or timed on it); give max_in_flight in its [[line.route]] tables",
        ),
        (
            format!("{line}serial = {{ path = \"/dev/ttyS0\", framing = \"rtu\", direction = \"rts\" }}\n[[line.route]]\naddress = \"h:1\"\n"),
            "3:62: line[0].serial.direction: means nothing on a master line (the device is the master: the gateway only answers it, with no gap, echo or transmitter of its own to keep); for RS-485 let the adapter or the kernel switch it (rs485 = true)",
        ),
        (
            format!("{line}[line.serial]\nrs485 = true\necho = true\n[[line.route]]\naddress = \"h:1\"\n"),
            "5:8: line[0].serial.echo: means nothing on a master line (the device is the master: the gateway only answers it, with no gap, echo or transmitter of its own to keep); its [line.serial] takes only path, baud_rate, data_bits, parity, stop_bits, flow_control, framing, low_latency, silence_floor_ms, rs485, rs485_delay_before_send_ms, rs485_delay_after_send_ms",
        ),
        (
            format!("{line}units = [1]\n[[line.route]]\naddress = \"h:1\"\n"),
            "3:9: line[0].units: a master line routes by the units of its [[line.route]] tables",
        ),
    ] {
        let e = parse(&text, F).expect_err(&text).to_string();
        assert!(
            e.starts_with(&format!("{F}:{want}")),
            "{text}\n{e:?}\nshould start with {want:?}"
        );
    }
}

/// config/mbgate.toml's commented example of a master line, uncommented, is valid.
#[test]
fn the_shipped_example_is_valid() {
    let text = include_str!("../../config/mbgate.toml");
    let start = text
        .find("# [[line]]\n# role = \"master\"")
        .expect("the example");
    let example: String = text[start..]
        .lines()
        .take_while(|l| l.starts_with('#'))
        .map(|l| format!("{}\n", l.trim_start_matches('#').trim_start()))
        .collect();
    let cfg = parse(&example, F).unwrap_or_else(|e| panic!("{e}\n{example}"));
    assert_eq!(cfg.lines[0].master.as_ref().unwrap().routes.len(), 2);
}

/// A master line beside a line of slaves: both read, the master line needing no
/// `units`; the slave line still must say its units, two lines on one port are
/// refused naming the second's port, and a passive route on a listener's address
/// naming the route.
#[test]
fn a_master_line_stands_beside_other_lines() {
    let master =
        "[[line]]\nrole = \"master\"\nserial = { path = \"/dev/ttyS1\", framing = \"rtu\" }\n\
                  [[line.route]]\naddress = \"h:1\"\nresponse_timeout_ms = 300\n";
    let slaves = |path: &str, units: &str| {
        format!("[[line]]\n{units}serial = {{ path = \"{path}\", framing = \"rtu\" }}\n")
    };
    let text = format!("{master}{}", slaves("/dev/ttyS2", "units = [1, 2]\n"));
    let cfg = parse(&text, F).unwrap();
    assert_eq!(cfg.lines.len(), 2);
    assert!(
        cfg.lines[0].master.is_some(),
        "the master line, as written first"
    );
    let printed = to_toml_lines(&cfg);
    assert_eq!(parse(&printed, F).unwrap(), cfg, "{printed}");

    for (text, want) in [
        (
            format!("{master}{}", slaves("/dev/ttyS2", "")),
            "7:1: line[1].units: missing: with several lines, each says which unit ids it serves",
        ),
        (
            format!(
                "{}{}[[listen]]\naddress = \"127.0.0.1:5021\"\n",
                master.replace("address = \"h:1\"", "listen = \"127.0.0.1:5021\""),
                slaves("/dev/ttyS2", "units = [1]\n")
            ),
            "1:1: line[0].route[0].listen: 127.0.0.1:5021 is listen[0]'s address too: each socket has its own",
        ),
        (
            format!("{master}{}", slaves("/dev/ttyS1", "units = [1]\n")),
            "9:19: line[1].serial.path: the same as line[0]'s (\"/dev/ttyS1\"): each line has its own port or address",
        ),
    ] {
        let e = parse(&text, F).expect_err(&text).to_string();
        assert!(
            e.starts_with(&format!("{F}:{want}")),
            "{text}\n{e:?}\nshould start with {want:?}"
        );
    }
}
