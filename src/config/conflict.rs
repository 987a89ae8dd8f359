//! Two keys whose values contradict each other (a key above the key it must not
//! exceed, a value another key's value rules out): refused with both named, rather
//! than one silently capped.

use super::{Config, Direction, FlowControl, Framing, GpioLine, Key, KEYS};

/// Two keys whose values contradict each other: a key above the key it must not
/// exceed (`at_most` in [`settings!`]), or a value another key's value rules out.
pub(crate) struct Conflict {
    pub(crate) key: &'static Key,
    pub(crate) other: &'static Key,
    clash: Clash,
}

enum Clash {
    /// `key` is above `other`.
    Exceeds {
        value: i128,
        limit: i128,
        why: &'static str,
    },
    /// `key`'s value cannot go with `other`'s: the words after the other key's name.
    Excludes(String),
}

impl Conflict {
    /// The message, with the keys under `table` (`line[0].`, or none): the other key
    /// named with its section.
    pub(crate) fn message(&self, table: &str) -> String {
        let (section, name) = (self.other.section, self.other.name);
        let other = format!("{table}{section}.{name}");
        match &self.clash {
            Clash::Exceeds { value, limit, why } => {
                format!("must not exceed {other} ({limit}), got {value}: {why}")
            }
            Clash::Excludes(why) => format!("cannot go with {other}{why}"),
        }
    }
}

/// The key `section.name` of [`KEYS`].
fn key(section: &str, name: &str) -> &'static Key {
    KEYS.iter()
        .find(|k| k.section == section && k.name == name)
        .expect("a declared key")
}

impl Config {
    /// The first pair of keys whose values contradict each other, if any (the
    /// keys of [`KEYS`]: of the first line, the first listener and the gateway; the
    /// file reader asks each line's in turn). Refused rather than one silently capped: the operator meant one of them and mbgate
    /// cannot tell which.
    pub(crate) fn conflict(&self) -> Option<Conflict> {
        let exceeds = KEYS.iter().find_map(|key| {
            let (other, why) = key.at_most?;
            let other = KEYS
                .iter()
                .find(|k| k.section == key.section && k.name == other)?;
            let number = |k: &Key| (k.get)(self).parse::<i128>().ok();
            let (value, limit) = (number(key)?, number(other)?);
            let c = Conflict {
                key,
                other,
                clash: Clash::Exceeds { value, limit, why },
            };
            (value > limit).then_some(c)
        });
        exceeds
            .or_else(|| self.direction_conflict())
            .or_else(|| self.flow_conflict())
            .or_else(|| self.guard_conflict())
    }

    /// `relay.timeout_guard_ms = 0` on an RTU or ASCII line. A device that drops the
    /// requests it gets while busy answers a request that timed out late, in the
    /// window of the next one, which it never read; nothing in an RTU or ASCII frame
    /// tells that late answer from the next request's: only the guard, the quiet after
    /// a timeout, keeps it off (docs/reliability.md "RTU and ASCII", 3). A device that
    /// answers what it holds in order needs no guard (each request that timed out is
    /// owed, and its late answer pays it); 0 would turn the defence against the other
    /// kind off.
    fn guard_conflict(&self) -> Option<Conflict> {
        let line = &self.lines[0];
        let serial = matches!(line.serial.framing, Framing::Rtu | Framing::Ascii);
        (serial && line.relay.timeout_guard_ms == 0).then(|| Conflict {
            key: key("relay", "timeout_guard_ms"),
            other: key("serial", "framing"),
            clash: Clash::Excludes(format!(
                " = {:?}: a late answer from a device that dropped the next request while \
                 busy is kept off that request only by the guard; set 1 or more (100 by \
                 default)",
                line.serial.framing.name()
            )),
        })
    }

    /// XON/XOFF flow control on a binary framing: on RTU and MBAP lines any byte of a
    /// frame may be 0x11 or 0x13 (a length, a register value, a CRC), which the
    /// kernel would take for XON and XOFF, drop from the frame, and stop or start the
    /// gateway's output by; ASCII frames carry only printable characters, CR and LF
    /// (docs/rtu-ascii.md).
    fn flow_conflict(&self) -> Option<Conflict> {
        let s = &self.lines[0].serial;
        (s.flow_control == FlowControl::Software && s.framing != Framing::Ascii).then(|| Conflict {
            key: key("serial", "flow_control"),
            other: key("serial", "framing"),
            clash: Clash::Excludes(format!(
                " = {:?}: software flow control takes the bytes 0x11 and 0x13 for XON \
                     and XOFF, and any byte of a binary frame may be one (a length, a \
                     value, a CRC); use flow_control = \"hardware\" or \"none\", or \
                     framing = \"ascii\"",
                s.framing.name()
            )),
        })
    }

    /// `serial.direction` against the keys it cannot go with (docs/rs485.md).
    fn direction_conflict(&self) -> Option<Conflict> {
        let s = &self.lines[0].serial;
        let excludes = |name: &str, other: &str, why: String| Conflict {
            key: key("serial", name),
            other: key("serial", other),
            clash: Clash::Excludes(why),
        };
        let method = s.direction.name();
        match s.direction {
            Direction::None => None,
            _ if s.rs485 => Some(excludes(
                "direction",
                "rs485",
                format!(
                    " = true: the kernel's RS-485 mode switches the transmitter itself; \
                     set rs485 = false for direction = {method:?}, or direction = \"none\""
                ),
            )),
            _ if s.framing == Framing::Mbap => Some(excludes(
                "direction",
                "framing",
                " = \"mbap\": an MBAP line may have a reply coming while it sends; the \
                 gateway switches the transmitter on RTU and ASCII lines, one request at a time"
                    .into(),
            )),
            Direction::Rts if s.flow_control == FlowControl::Hardware => Some(excludes(
                "direction",
                "flow_control",
                " = \"hardware\": RTS/CTS flow control drives RTS itself; set flow_control = \
                 \"none\" for direction = \"rts\""
                    .into(),
            )),
            Direction::Gpio if s.direction_gpio_line == GpioLine::Unset => Some(excludes(
                "direction",
                "direction_gpio_line",
                " unset: direction = \"gpio\" needs the line, by offset (17) or by name \
                 (\"GPIO17\")"
                    .into(),
            )),
            _ => None,
        }
    }
}
