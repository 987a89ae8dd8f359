//! The effective setup in a few words a line: what `mbgate check-config` prints after
//! "OK", and what the log says of each line and listener at start. Each line says its
//! own framing and port settings, each listener the masters it takes, so a listener's
//! framing is never read as the line's.

use super::master::{MasterLine, Peer};
use super::{
    Config, Direction, FlowControl, Framing, GpioLine, LineConfig, ListenConfig, ListenFraming,
    Parity, SerialConfig,
};

/// `/dev/ttyUSB0: rtu, 19200 baud 8N1, no flow control, every unit`.
pub(crate) fn line(line: &LineConfig) -> String {
    let s = &line.serial;
    let framing = framing(s.framing);
    let device = match &line.tcp {
        Some(address) => {
            let framing = match s.framing {
                Framing::Mbap => "Modbus/TCP",
                Framing::Rtu => "RTU over TCP",
                Framing::Ascii => "ASCII over TCP",
            };
            format!("{address} (a device on the network): {framing}")
        }
        None => {
            let flow = match s.flow_control {
                FlowControl::None => "no flow control",
                FlowControl::Hardware => "RTS/CTS flow control",
                FlowControl::Software => "XON/XOFF flow control",
            };
            let direction = match direction(s) {
                Some(d) => format!(", {d}"),
                None => String::new(),
            };
            format!(
                "{}: {framing}, {} baud {}, {flow}{direction}",
                s.path,
                s.baud_rate,
                char_format(s)
            )
        }
    };
    if let Some(master) = &line.master {
        return format!("{device}; the device is the master: {}", routes(master));
    }
    let units = &line.units;
    let served = if units.every() {
        "every unit".to_owned()
    } else {
        let mut parts = Vec::new();
        if !units.ids.is_empty() {
            let ids: Vec<u8> = units.ids.iter().copied().collect();
            parts.push(format!("units {}", list(&ids)));
        }
        for (master, on_line) in &units.remap {
            parts.push(format!("unit {master} as {on_line}"));
        }
        parts.join(", ")
    };
    format!("{device}, {served}")
}

/// A master line's routes: `units 1-3 -> 10.0.0.5:502; other units -> ...`.
fn routes(master: &MasterLine) -> String {
    let routes: Vec<String> = master
        .routes
        .iter()
        .map(|r| {
            let from = match (&r.peer, &r.allow) {
                (Peer::Listen(_), Some(allow)) => format!(" from {allow}"),
                (Peer::Listen(_), None) => " from anywhere (no allow list)".to_owned(),
                (Peer::Connect(_), _) => String::new(),
            };
            match r.units.as_slice() {
                [] => format!("other units -> {}{from}", r.peer),
                u => format!("units {} -> {}{from}", list(u), r.peer),
            }
        })
        .collect();
    routes.join("; ")
}

/// `127.0.0.1:5502 for Modbus/TCP masters`.
pub(crate) fn listener(l: &ListenConfig) -> String {
    match l.transport {
        super::Transport::Udp => format!("{} (UDP) for Modbus/UDP masters", l.tcp.listen),
        super::Transport::Tcp => format!("{} for {}", l.tcp.listen, masters(l.framing)),
    }
}

/// Who connects to a listener of this framing.
pub(crate) fn masters(framing: ListenFraming) -> &'static str {
    match framing {
        ListenFraming::Mbap => "Modbus/TCP masters",
        ListenFraming::Rtu => "RTU-over-TCP masters",
    }
}

/// Each dial in a line (`mbgate check-config`, the start-up log).
pub(crate) fn dial(d: &super::dial::DialConfig) -> String {
    let mut s = format!(
        "dialing {} for {}, backoff {} to {} ms",
        d.address,
        masters(d.framing),
        d.backoff_min_ms,
        d.backoff_max_ms
    );
    if !d.identity.is_empty() {
        s += &format!(", identity of {} bytes", d.identity.len());
    }
    if !d.heartbeat.is_empty() {
        s += &format!(
            ", heartbeat of {} bytes after {} ms quiet",
            d.heartbeat.len(),
            d.heartbeat_ms
        );
    }
    if let Some(t) = &d.tls {
        s += ", over TLS";
        if let Some(r) = &t.default_role {
            s += &format!(" (default role {r:?})");
        }
    }
    if d.priority != 0 {
        s += &format!(", priority class {}", d.priority);
    }
    if d.policy.read_only {
        s += ", read only";
    } else if !d.policy.write.is_empty() {
        s += &format!(", {} write rules", d.policy.write.len());
    }
    s
}

/// Who switches the line's RS-485 transmitter, in words (`check-config`, the start-up
/// log, the status page); `None` when nobody is asked to: the adapter does it by itself,
/// or the line is no RS-485 bus.
pub(crate) fn direction(s: &SerialConfig) -> Option<String> {
    let delays = || match (s.direction_delay_before_us, s.direction_delay_after_us) {
        (0, 0) => String::new(),
        (before, after) => {
            format!(", {before} µs before the first byte, {after} µs after the last")
        }
    };
    match s.direction {
        Direction::None if s.rs485 => {
            Some("RS-485 mode: the kernel switches the transmitter by RTS".into())
        }
        Direction::None => None,
        Direction::Rts => {
            let when = if s.direction_invert {
                "released"
            } else {
                "asserted"
            };
            Some(format!(
                "the gateway switches the transmitter by RTS ({when} while sending{})",
                delays()
            ))
        }
        Direction::Gpio => {
            let level = if s.direction_invert { "low" } else { "high" };
            let line = match &s.direction_gpio_line {
                GpioLine::Offset(n) => format!("line {n}"),
                GpioLine::Name(n) => format!("line {n:?}"),
                GpioLine::Unset => "no line".into(),
            };
            let chip = match s.direction_gpio_chip.as_str() {
                "" => match &s.direction_gpio_line {
                    GpioLine::Name(_) => "any chip".into(),
                    _ => "gpiochip0".into(),
                },
                c => c.to_owned(),
            };
            Some(format!(
                "the gateway switches the transmitter by GPIO {line} of {chip} ({level} while sending{})",
                delays()
            ))
        }
    }
}

/// A line's framing in words.
fn framing(f: Framing) -> &'static str {
    match f {
        Framing::Mbap => "MBAP (serial Modbus/TCP)",
        Framing::Rtu => "RTU",
        Framing::Ascii => "ASCII",
    }
}

/// Unit ids with runs as ranges: `1, 2, 20-29`.
fn list(ids: &[u8]) -> String {
    let mut parts = Vec::new();
    let mut i = 0;
    while i < ids.len() {
        let mut j = i;
        while j + 1 < ids.len() && ids[j + 1] == ids[j].wrapping_add(1) {
            j += 1;
        }
        if j >= i + 2 {
            parts.push(format!("{}-{}", ids[i], ids[j]));
        } else {
            parts.extend(ids[i..=j].iter().map(u8::to_string));
        }
        i = j + 1;
    }
    parts.join(", ")
}

/// The whole setup, a line each: the lines, then the listeners and the metrics
/// listener (a master line has neither).
pub(crate) fn summary(cfg: &Config) -> String {
    let mut out = String::new();
    for l in &cfg.lines {
        out += &format!("line {}\n", line(l));
        for unit in l.unit_tables.describe(&l.relay) {
            out += &format!("  {unit}\n");
        }
    }
    if !cfg.serves_masters() {
        // Master lines listen for no masters and have no metrics listener.
        return out;
    }
    if cfg.dial_only {
        out += "no listener: the file only dials its masters and opens no port (add [[listen]] or [tcp] listen = \"ADDR\" for masters to connect in)\n";
    }
    for l in cfg.listeners.iter().filter(|_| !cfg.dial_only) {
        let priority = match l.priority {
            0 => String::new(),
            p => format!(", priority class {p}"),
        };
        out += &format!(
            "listening on {}, at most {} at once{priority}\n",
            listener(l),
            l.tcp.max_connections
        );
        // Who may connect and what they may do: TLS, the allow list, the roles
        // (docs/security.md shows these lines).
        for said in super::effective_access(l, &cfg.roles) {
            out += &format!("  # {said}\n");
        }
        if l.transport == super::Transport::Udp {
            let after = super::NOTIFIED_FOR.as_millis();
            out += &match l.notifications {
                true => format!(
                    "  # notifications: to each source for {after} ms after its last request\n"
                ),
                false => {
                    "  # notifications: none to its sources (notifications = true sends them)\n"
                        .into()
                }
            };
        }
    }
    for d in &cfg.dials {
        out += &format!("{}\n", dial(d));
    }
    let web = cfg.metrics.web_config.trim();
    out += &match cfg.metrics.listen {
        Some(a) if web.is_empty() => format!(
            "status page on http://{a}/, metrics on http://{a}/metrics (mbgate status --metrics {a})\n"
        ),
        // `mbgate check-config` adds who may read it, from the file.
        Some(a) => format!(
            "status page on {a}/, metrics on {a}/metrics, as {web} says\n"
        ),
        None => "no metrics listener (set [metrics] listen = \"127.0.0.1:9502\" for the status page and mbgate status)\n"
            .to_owned(),
    };
    out
}

/// A character's format as a port's settings are written: data bits, parity, stop
/// bits (`8N1`, `8E1`, `7O2`). The capture's line description carries it too, for a
/// replay's time on the wire (docs/capture.md).
pub(crate) fn char_format(s: &SerialConfig) -> String {
    let parity = match s.parity {
        Parity::None => 'N',
        Parity::Even => 'E',
        Parity::Odd => 'O',
    };
    format!("{}{parity}{}", s.data_bits, s.stop_bits)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::parse;

    #[test]
    fn a_file_in_a_few_lines() {
        let cfg = parse(
            "[[line]]\nunits = [1, 2, 3, 7]\nremap = { 11 = 1 }\n\
             serial = { path = \"/dev/ttyUSB1\", framing = \"rtu\", baud_rate = 9600, \
             parity = \"even\", flow_control = \"none\" }\n\
             [[line]]\nunits = [50]\ntcp = { address = \"10.0.0.5:502\" }\n\
             [[listen]]\naddress = \"0.0.0.0:502\"\n\
             [[listen]]\naddress = \"0.0.0.0:4001\"\nframing = \"rtu\"\n",
            "t.toml",
        )
        .unwrap();
        assert_eq!(
            summary(&cfg),
            "line /dev/ttyUSB1: RTU, 9600 baud 8E1, no flow control, units 1-3, 7, unit 11 as 1\n\
             line 10.0.0.5:502 (a device on the network): Modbus/TCP, units 50\n\
             listening on 0.0.0.0:502 for Modbus/TCP masters, at most 32 at once\n\
             \x20 # who: from everyone (no allow list), plain TCP\n\
             \x20 # what: read and write\n\
             listening on 0.0.0.0:4001 for RTU-over-TCP masters, at most 32 at once\n\
             \x20 # who: from everyone (no allow list), plain TCP\n\
             \x20 # what: read and write\n\
             no metrics listener (set [metrics] listen = \"127.0.0.1:9502\" for the status page and mbgate status)\n"
        );
    }

    /// A file that dials its masters and names no listener opens none, and says so;
    /// one that names a listener (`[tcp]` or `[[listen]]`) beside its dials listens.
    /// Printed and read back, each stays as it was.
    #[test]
    fn a_file_that_only_dials_opens_no_listener() {
        let dial = "[[dial]]\naddress = \"scada.example.net:502\"\n";
        let line = "[[line]]\nserial = { path = \"/dev/ttyUSB0\", framing = \"rtu\", flow_control = \"none\" }\n";
        let read = |text: String| parse(&text, "t.toml").unwrap();
        for only in [
            read(format!("[serial]\npath = \"/dev/ttyUSB0\"\n{dial}")),
            read(format!("{line}{dial}")),
        ] {
            assert!(only.dial_only && !only.listens());
            let said = summary(&only);
            assert!(
                said.contains("no listener: the file only dials its masters and opens no port")
                    && !said.contains("listening on"),
                "{said}"
            );
            assert!(said.contains("dialing scada.example.net:502"), "{said}");
            let printed = crate::config::to_toml(&only);
            assert_eq!(parse(&printed, "printed").unwrap(), only, "{printed}");
        }
        for listening in [
            read(format!("[tcp]\nlisten = \"0.0.0.0:502\"\n{dial}")),
            read(format!(
                "{line}[[listen]]\naddress = \"127.0.0.1:502\"\n{dial}"
            )),
            read("[serial]\npath = \"/dev/ttyUSB0\"\n".into()),
        ] {
            assert!(!listening.dial_only && listening.listens());
            let said = summary(&listening);
            assert!(said.contains("listening on"), "{said}");
            let printed = crate::config::to_toml(&listening);
            assert_eq!(parse(&printed, "printed").unwrap(), listening, "{printed}");
        }
    }

    /// Each way of switching the transmitter says itself, with its polarity and delays.
    #[test]
    fn the_direction_method_is_said() {
        let said = |extra: &str| {
            let text = format!(
                "[serial]\npath = \"/dev/ttyAMA0\"\nframing = \"rtu\"\nflow_control = \"none\"\n{extra}"
            );
            let cfg = parse(&text, "t.toml").unwrap();
            direction(&cfg.lines[0].serial)
        };
        assert_eq!(said(""), None);
        assert_eq!(
            said("rs485 = true\n").as_deref(),
            Some("RS-485 mode: the kernel switches the transmitter by RTS")
        );
        assert_eq!(
            said("direction = \"rts\"\n").as_deref(),
            Some("the gateway switches the transmitter by RTS (asserted while sending)")
        );
        assert_eq!(
            said("direction = \"rts\"\ndirection_invert = true\ndirection_delay_before_us = 50\n").as_deref(),
            Some("the gateway switches the transmitter by RTS (released while sending, 50 µs before the first byte, 0 µs after the last)")
        );
        assert_eq!(
            said("direction = \"gpio\"\ndirection_gpio_line = 17\n").as_deref(),
            Some("the gateway switches the transmitter by GPIO line 17 of gpiochip0 (high while sending)")
        );
        assert_eq!(
            said("direction = \"gpio\"\ndirection_gpio_line = \"GPIO17\"\ndirection_invert = true\n").as_deref(),
            Some("the gateway switches the transmitter by GPIO line \"GPIO17\" of any chip (low while sending)")
        );
    }

    /// The keys `direction` cannot go with are refused, naming both.
    #[test]
    fn direction_refuses_what_it_cannot_go_with() {
        let refused = |text: &str| parse(text, "t.toml").unwrap_err().to_string();
        let e = refused("[serial]\nframing = \"rtu\"\nflow_control = \"none\"\ndirection = \"rts\"\nrs485 = true\n");
        assert!(
            e.contains("serial.direction") && e.contains("serial.rs485"),
            "{e}"
        );
        let e = refused("[serial]\nframing = \"rtu\"\ndirection = \"rts\"\n");
        assert!(e.contains("serial.flow_control = \"hardware\""), "{e}");
        let e = refused("[serial]\ndirection = \"gpio\"\ndirection_gpio_line = 4\n");
        assert!(e.contains("serial.framing = \"mbap\""), "{e}");
        let e = refused("[serial]\nframing = \"ascii\"\ndirection = \"gpio\"\n");
        assert!(e.contains("serial.direction_gpio_line unset"), "{e}");
        let e = refused("[[line]]\nserial = { framing = \"rtu\", direction = \"rts\" }\n");
        assert!(e.contains("line[0].serial.direction"), "{e}");
        let e = refused(
            "[serial]\nframing = \"rtu\"\ndirection = \"gpio\"\ndirection_gpio_line = -1\n",
        );
        assert!(e.contains("-1 is no line offset"), "{e}");
    }
}
