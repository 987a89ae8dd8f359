//! What `mbgate scan` sends and how it judges what comes back, pure: the order of the
//! settings tried, the read requests, the search of a reply for a frame with a good
//! CRC or LRC, the give-up rule of a setting, and the identity a device reports
//! (FC 43/14, FC 17: Modbus Application Protocol V1.1b3 §6.21, §6.13).

use crate::frame::serial::Codec;
use crate::frame::{ascii, rtu};
use crate::tools::wire::uart::Format;

/// A serial framing the scan tries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum SerialFraming {
    /// Modbus RTU: binary, CRC-16.
    Rtu,
    /// Modbus ASCII: hex between `:` and CR LF, LRC.
    Ascii,
}

impl SerialFraming {
    /// As the configuration spells it.
    pub(crate) fn name(self) -> &'static str {
        match self {
            SerialFraming::Rtu => "rtu",
            SerialFraming::Ascii => "ascii",
        }
    }

    /// The framing itself, whose frames (and their lengths) `crate::frame` makes:
    /// this enum is only the flag's values, which the pure frame code stays free of.
    pub(crate) fn codec(self) -> Codec {
        match self {
            SerialFraming::Rtu => Codec::Rtu,
            SerialFraming::Ascii => Codec::Ascii,
        }
    }
}

/// The baud rates tried by default, most used first.
pub(crate) const DEFAULT_BAUDS: [u32; 8] = [19200, 9600, 115200, 38400, 57600, 4800, 2400, 1200];

/// The formats tried by default: the specification's default (8E1), the most used in
/// practice (8N1), the specification's no-parity form (8N2), odd parity.
pub(crate) const DEFAULT_FORMATS: [&str; 4] = ["8E1", "8N1", "8N2", "8O1"];

/// The settings at which every unit id is tried, in this order (docs/scan.md, "What
/// it tries"): RTU then ASCII at 19 200 and 9600 baud, 8E1 and 8N1, most buses' settings.
/// Elsewhere a setting is left after `--give-up` silent units.
pub(crate) const WIDE: [(u32, &str, SerialFraming); 8] = [
    (19200, "8E1", SerialFraming::Rtu),
    (9600, "8N1", SerialFraming::Rtu),
    (19200, "8N1", SerialFraming::Rtu),
    (9600, "8E1", SerialFraming::Rtu),
    (19200, "8E1", SerialFraming::Ascii),
    (9600, "8N1", SerialFraming::Ascii),
    (19200, "8N1", SerialFraming::Ascii),
    (9600, "8E1", SerialFraming::Ascii),
];

/// One setting of the port, with the framings tried on it while it is open.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct ProbeSetting {
    /// Bits per second.
    pub(crate) baud: u32,
    /// Data bits, parity, stop bits.
    pub(crate) format: Format,
    /// Tried in this order.
    pub(crate) framings: Vec<SerialFraming>,
}

/// Every combination of `bauds` × `formats` × `framings`, in that order of importance,
/// except that `first` (the likeliest: 19200 8E1 RTU, the specification's default, and
/// 9600 8N1 RTU, the most common) go before all. Consecutive tries at one baud rate and
/// format share one open of the port.
pub(crate) fn order(
    bauds: &[u32],
    formats: &[Format],
    framings: &[SerialFraming],
    first: &[(u32, Format, SerialFraming)],
) -> Vec<ProbeSetting> {
    let wanted = |&(b, f, fr): &(u32, Format, SerialFraming)| {
        bauds.contains(&b) && formats.contains(&f) && framings.contains(&fr)
    };
    let mut triples: Vec<(u32, Format, SerialFraming)> =
        first.iter().copied().filter(wanted).collect();
    for &b in bauds {
        for &f in formats {
            for &fr in framings {
                if !triples.contains(&(b, f, fr)) {
                    triples.push((b, f, fr));
                }
            }
        }
    }
    let mut out: Vec<ProbeSetting> = Vec::new();
    for (baud, format, framing) in triples {
        match out.last_mut() {
            Some(s) if s.baud == baud && s.format == format => s.framings.push(framing),
            _ => out.push(ProbeSetting {
                baud,
                format,
                framings: vec![framing],
            }),
        }
    }
    out
}

/// The read a unit is asked first: FC 03 (or 04) of one register at address 0.
pub(crate) fn read_one(function: u8) -> [u8; 5] {
    [function, 0x00, 0x00, 0x00, 0x01]
}

/// FC 43 / MEI 14, read device identification, basic stream (01) from object 0.
pub(crate) const DEVICE_ID: [u8; 4] = [0x2B, 0x0E, 0x01, 0x00];

/// FC 17, report server id.
pub(crate) const SERVER_ID: [u8; 1] = [0x11];

/// What came back for a request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Heard {
    /// Nothing at all (or only the request's own echo).
    Nothing,
    /// Bytes, but no frame with a good check for this request.
    Garbage(usize),
    /// A whole frame with a good check that does not answer the request: another
    /// function's (a device that answers everything with one frame, another master's
    /// traffic). It proves nothing about the unit asked.
    Unanswering {
        /// The unit it is from.
        unit: u8,
        /// Its function code.
        function: u8,
    },
    /// A frame with a good check whose function is the request's (or its exception).
    Frame {
        /// The unit that answered.
        unit: u8,
        /// Its PDU.
        pdu: Vec<u8>,
    },
}

/// The most bytes searched for a frame: a reply to these requests is far shorter, and
/// the search is quadratic.
const SEARCH_LIMIT: usize = 600;

/// Looks in `bytes` for a frame with a good CRC (RTU) or LRC (ASCII) answering
/// `function`: its function code, or it with the exception bit (for a read, either
/// read). The request's own echo
/// at the front (an RS-232 loopback, a 2-wire RS-485 adapter) is skipped. Any start
/// and length is tried, so garbage before or after a reply does not hide it.
pub(crate) fn judge(framing: SerialFraming, request: &[u8], function: u8, bytes: &[u8]) -> Heard {
    let bytes = bytes.strip_prefix(request).unwrap_or(bytes);
    let bytes = &bytes[..bytes.len().min(SEARCH_LIMIT)];
    if bytes.is_empty() {
        return Heard::Nothing;
    }
    // The two reads answer each other: FC 04 is asked where FC 03 got nothing, and
    // FC 03's late reply may come while FC 04 is asked.
    let reads = |f: u8| f == 3 || f == 4;
    let answers = |fc: u8| fc & 0x7F == function || (reads(function) && reads(fc & 0x7F));
    match framing {
        SerialFraming::Rtu => {
            for i in 0..bytes.len() {
                if bytes.len() - i < 4 || !answers(bytes[i + 1]) {
                    continue;
                }
                for j in i + 4..=bytes.len() {
                    if let Some((unit, pdu)) = rtu::decode(&bytes[i..j]) {
                        return Heard::Frame {
                            unit,
                            pdu: pdu.to_vec(),
                        };
                    }
                }
            }
            // Only the whole of what came, as one frame: a search of every start and
            // length for any function would find a good CRC in garbage by chance.
            if let Some((unit, pdu)) = rtu::decode(bytes) {
                if let Some(&function) = pdu.first() {
                    return Heard::Unanswering { unit, function };
                }
            }
        }
        SerialFraming::Ascii => {
            let mut start = 0;
            let mut other = None;
            while let Some(colon) = bytes[start..].iter().position(|&b| b == b':') {
                let from = start + colon;
                let Some(lf) = bytes[from..].iter().position(|&b| b == b'\n') else {
                    break;
                };
                if let Some((unit, pdu)) = ascii::decode(&bytes[from..=from + lf]) {
                    match pdu.first() {
                        Some(&fc) if answers(fc) => return Heard::Frame { unit, pdu },
                        Some(&function) => {
                            other = other.or(Some(Heard::Unanswering { unit, function }))
                        }
                        None => {}
                    }
                }
                start = from + 1;
            }
            if let Some(other) = other {
                return other;
            }
        }
    }
    Heard::Garbage(bytes.len())
}

/// A reply's PDU in a few words: the register read, or the exception.
pub(crate) fn describe(pdu: &[u8]) -> String {
    match pdu {
        [fc, code, ..] if fc & 0x80 != 0 => {
            format!("FC {:02}: exception {code:02X}", fc & 0x7F)
        }
        [fc, 2, hi, lo] => format!("FC {fc:02}: {}", u16::from_be_bytes([*hi, *lo])),
        [fc, ..] => format!("FC {fc:02}: {} bytes", pdu.len() - 1),
        [] => String::new(),
    }
}

/// Why a unit's identity (FC 43/14 or FC 17) is not known.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub(crate) enum NoIdentity {
    /// Not asked: the scan stopped first, or the unit was found some other way.
    #[error("not asked")]
    NotAsked,
    /// Asked, and nothing came.
    #[error("no answer")]
    NoAnswer,
    /// The unit answered with this exception code (0x01: it has no such function).
    #[error("exception {0:02X}")]
    Exception(u8),
    /// What came is no reply to the function asked.
    #[error("a malformed reply")]
    Malformed,
}

/// The objects of a read device identification reply, `(id, value)`, or why not.
pub(crate) fn device_id(pdu: &[u8]) -> Result<Vec<(u8, String)>, NoIdentity> {
    if let [fc, code, ..] = pdu {
        if fc & 0x80 != 0 {
            return Err(NoIdentity::Exception(*code));
        }
    }
    let [0x2B, 0x0E, _code, _conformity, _more, _next, count, rest @ ..] = pdu else {
        return Err(NoIdentity::Malformed);
    };
    let mut objects = Vec::new();
    let mut rest = rest;
    for _ in 0..*count {
        let [id, len, tail @ ..] = rest else { break };
        let len = usize::from(*len).min(tail.len());
        objects.push((*id, String::from_utf8_lossy(&tail[..len]).into_owned()));
        rest = &tail[len..];
    }
    Ok(objects)
}

/// The data of a report server id reply, or why not.
pub(crate) fn server_id(pdu: &[u8]) -> Result<Vec<u8>, NoIdentity> {
    match pdu {
        [fc, code, ..] if fc & 0x80 != 0 => Err(NoIdentity::Exception(*code)),
        [0x11, count, data @ ..] => Ok(data[..usize::from(*count).min(data.len())].to_vec()),
        _ => Err(NoIdentity::Malformed),
    }
}

/// Bytes shown as text where they are printable, else as hex.
pub(crate) fn printable(data: &[u8]) -> String {
    if !data.is_empty() && data.iter().all(|b| (0x20..0x7F).contains(b)) {
        String::from_utf8_lossy(data).into_owned()
    } else {
        data.iter().map(|b| format!("{b:02X}")).collect()
    }
}

/// A report server id's data for a person: the run indicator status (0x00 OFF, 0xFF
/// ON), when it is the last byte after printable text, said as such.
pub(crate) fn server_id_text(data: &[u8]) -> String {
    match data.split_last() {
        Some((&run @ (0x00 | 0xFF), text))
            if !text.is_empty() && text.iter().all(|b| (0x20..0x7F).contains(b)) =>
        {
            let on = if run == 0xFF { "ON" } else { "OFF" };
            format!("{}, run indicator {on}", String::from_utf8_lossy(text))
        }
        _ => printable(data),
    }
}

/// The units of one setting, and when to leave it: a setting is proven by any frame
/// with a good check; until then, after `give_up` units have got no such frame, it is
/// left (at a wrong baud rate or parity a device hears garbage and stays silent, so
/// every further unit would cost a whole timeout for nothing). Once proven, every unit
/// is tried.
#[derive(Debug, Clone)]
pub(crate) struct AtSetting {
    units: Vec<u8>,
    next: usize,
    give_up: usize,
    /// A frame with a good check came at this setting.
    pub(crate) proven: bool,
    /// Some try got bytes without a frame.
    pub(crate) garbage: bool,
    /// The first whole frame with a good check that answered no request, as
    /// `(unit, function)`.
    pub(crate) unanswering: Option<(u8, u8)>,
}

impl AtSetting {
    /// Starts on `units`.
    pub(crate) fn new(units: Vec<u8>, give_up: usize) -> AtSetting {
        AtSetting {
            units,
            next: 0,
            give_up,
            proven: false,
            garbage: false,
            unanswering: None,
        }
    }

    /// The unit to try next, if the setting is not done with.
    pub(crate) fn next_unit(&self) -> Option<u8> {
        if !self.proven && self.next >= self.give_up {
            return None;
        }
        self.units.get(self.next).copied()
    }

    /// What the unit last returned by [`next_unit`](Self::next_unit) got.
    pub(crate) fn record(&mut self, heard: &Heard) {
        self.next += 1;
        match heard {
            Heard::Frame { .. } => self.proven = true,
            Heard::Garbage(_) => self.garbage = true,
            Heard::Unanswering { unit, function } => {
                self.unanswering = self.unanswering.or(Some((*unit, *function)))
            }
            Heard::Nothing => {}
        }
    }

    /// Tries left at most, as things stand (for the time left).
    pub(crate) fn left(&self) -> usize {
        let end = if self.proven {
            self.units.len()
        } else {
            self.give_up.min(self.units.len())
        };
        end.saturating_sub(self.next)
    }
}

/// A part of a unit list that is not a unit id or a range.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0:?}: a unit id is 1 to 247, a range A-B")]
pub(crate) struct BadUnits(String);

/// A list of unit ids: `1-247`, `1,2,10-20`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct UnitList(pub(crate) Vec<u8>);

impl std::str::FromStr for UnitList {
    type Err = BadUnits;

    fn from_str(s: &str) -> Result<UnitList, BadUnits> {
        let mut out = Vec::new();
        for part in s.split(',') {
            let bad = || BadUnits(part.to_owned());
            let id = |x: &str| match x.trim().parse::<u8>() {
                Ok(n @ 1..=247) => Ok(n),
                _ => Err(bad()),
            };
            match part.split_once('-') {
                Some((a, b)) => {
                    let (a, b) = (id(a)?, id(b)?);
                    if a > b {
                        return Err(bad());
                    }
                    out.extend(a..=b);
                }
                None => out.push(id(part)?),
            }
        }
        out.dedup();
        Ok(UnitList(out))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn f(s: &str) -> Format {
        s.parse().unwrap()
    }

    #[test]
    fn the_likeliest_settings_come_first_and_share_an_open() {
        let formats: Vec<Format> = DEFAULT_FORMATS.iter().map(|s| f(s)).collect();
        let first = [
            (19200, f("8E1"), SerialFraming::Rtu),
            (9600, f("8N1"), SerialFraming::Rtu),
        ];
        let o = order(
            &DEFAULT_BAUDS,
            &formats,
            &[SerialFraming::Rtu, SerialFraming::Ascii],
            &first,
        );
        assert_eq!(o[0].baud, 19200);
        assert_eq!(o[0].format, f("8E1"));
        assert_eq!(o[0].framings, vec![SerialFraming::Rtu]);
        assert_eq!((o[1].baud, o[1].format), (9600, f("8N1")));
        // Every combination once: 8 × 4 × 2.
        let tries: usize = o.iter().map(|s| s.framings.len()).sum();
        assert_eq!(tries, 64);
        // 19200 8E1 ASCII comes later, in its own open.
        assert_eq!(o[2].baud, 19200);
        assert_eq!(o[2].framings, vec![SerialFraming::Ascii]);
        // A first setting not asked for is not tried.
        let o = order(&[1200], &[f("8N1")], &[SerialFraming::Ascii], &first);
        assert_eq!(o.len(), 1);
        assert_eq!(o[0].framings, vec![SerialFraming::Ascii]);
    }

    #[test]
    fn a_good_frame_is_found_among_echo_and_garbage() {
        let req = rtu::encode(5, &read_one(3));
        let reply = rtu::encode(5, &[0x03, 0x02, 0x00, 0xFF]);
        assert_eq!(
            judge(SerialFraming::Rtu, &req, 3, &reply),
            Heard::Frame {
                unit: 5,
                pdu: vec![0x03, 0x02, 0x00, 0xFF]
            }
        );
        // Echo first, garbage around.
        let mut noisy = req.clone();
        noisy.extend([0x00, 0xF8]);
        noisy.extend(&reply);
        noisy.push(0x77);
        assert!(matches!(
            judge(SerialFraming::Rtu, &req, 3, &noisy),
            Heard::Frame { unit: 5, .. }
        ));
        // An exception is a reply.
        let exc = rtu::encode(5, &[0x83, 0x02]);
        assert!(matches!(
            judge(SerialFraming::Rtu, &req, 3, &exc),
            Heard::Frame { .. }
        ));
        // The echo alone is nothing; a bad CRC is garbage; a good frame of another
        // function is not this request's.
        assert_eq!(judge(SerialFraming::Rtu, &req, 3, &req), Heard::Nothing);
        let mut bad = reply.clone();
        bad[3] ^= 1;
        assert_eq!(judge(SerialFraming::Rtu, &req, 3, &bad), Heard::Garbage(7));
        let other = rtu::encode(5, &[0x11, 0x02, 0x00, 0xFF]);
        assert_eq!(
            judge(SerialFraming::Rtu, &req, 3, &other),
            Heard::Unanswering {
                unit: 5,
                function: 0x11
            }
        );
        let mut other_noisy = other.clone();
        other_noisy.push(0x77);
        assert_eq!(
            judge(SerialFraming::Rtu, &req, 3, &other_noisy),
            Heard::Garbage(8)
        );
        // FC 03's late reply while FC 04 is asked is a reply.
        let late = rtu::encode(5, &[0x03, 0x02, 0x00, 0xFF]);
        let req4 = rtu::encode(5, &read_one(4));
        assert!(matches!(
            judge(SerialFraming::Rtu, &req4, 4, &late),
            Heard::Frame { .. }
        ));
        // ASCII: the LRC is checked.
        let req = ascii::encode(7, &read_one(4));
        let reply = ascii::encode(7, &[0x04, 0x02, 0x07, 0xD0]);
        let mut noisy = b"\x00zz".to_vec();
        noisy.extend(&reply);
        assert!(matches!(
            judge(SerialFraming::Ascii, &req, 4, &noisy),
            Heard::Frame { unit: 7, .. }
        ));
        let mut bad = reply.clone();
        bad[5] = b'F';
        assert!(matches!(
            judge(SerialFraming::Ascii, &req, 4, &bad),
            Heard::Garbage(_)
        ));
        assert_eq!(judge(SerialFraming::Ascii, &req, 4, b""), Heard::Nothing);
        let other = ascii::encode(7, &[0x06, 0x00, 0x00, 0x00, 0x2A]);
        assert_eq!(
            judge(SerialFraming::Ascii, &req, 4, &other),
            Heard::Unanswering {
                unit: 7,
                function: 6
            }
        );
    }

    #[test]
    fn a_setting_is_left_after_give_up_units_unless_proven() {
        let mut s = AtSetting::new((1..=247).collect(), 3);
        let mut tried = Vec::new();
        while let Some(u) = s.next_unit() {
            tried.push(u);
            s.record(&Heard::Nothing);
        }
        assert_eq!(tried, vec![1, 2, 3]);
        assert!(!s.proven);
        // Garbage does not prove it either.
        let mut s = AtSetting::new((1..=247).collect(), 2);
        s.record(&Heard::Garbage(3));
        s.record(&Heard::Garbage(3));
        assert_eq!(s.next_unit(), None);
        assert!(s.garbage);
        // A frame at the third unit: every unit is tried.
        let mut s = AtSetting::new((1..=10).collect(), 3);
        let mut n = 0;
        while let Some(u) = s.next_unit() {
            n += 1;
            let heard = if u == 3 {
                Heard::Frame {
                    unit: 3,
                    pdu: vec![3, 2, 0, 0],
                }
            } else {
                Heard::Nothing
            };
            s.record(&heard);
            if u == 3 {
                assert_eq!(s.left(), 7);
            }
        }
        assert_eq!(n, 10);
    }

    #[test]
    fn identities_parse() {
        let pdu = [
            0x2B, 0x0E, 0x01, 0x01, 0x00, 0x00, 0x02, 0x00, 0x03, b'A', b'C', b'M', 0x01, 0x02,
            b'X', b'1',
        ];
        assert_eq!(
            device_id(&pdu).unwrap(),
            vec![(0, "ACM".to_string()), (1, "X1".to_string())]
        );
        assert_eq!(device_id(&[0xAB, 0x01]), Err(NoIdentity::Exception(1)));
        assert_eq!(NoIdentity::Exception(1).to_string(), "exception 01");
        assert_eq!(server_id(&[0x11]), Err(NoIdentity::Malformed));
        assert_eq!(
            server_id(&[0x11, 0x03, 0x0A, 0xFF, 0x00]).unwrap(),
            vec![0x0A, 0xFF, 0x00]
        );
        assert_eq!(printable(b"pymodbus"), "pymodbus");
        assert_eq!(
            server_id_text(b"pymodbus\xFF"),
            "pymodbus, run indicator ON"
        );
        assert_eq!(server_id_text(&[0x0A, 0x00]), "0A00");
        assert_eq!(printable(&[0x0A, 0xFF]), "0AFF");
        assert_eq!(describe(&[0x03, 0x02, 0x00, 0xFF]), "FC 03: 255");
        assert_eq!(describe(&[0x84, 0x02]), "FC 04: exception 02");
    }

    #[test]
    fn unit_lists_parse() {
        assert_eq!("1-3,7".parse::<UnitList>().unwrap().0, vec![1, 2, 3, 7]);
        assert_eq!("1-247".parse::<UnitList>().unwrap().0.len(), 247);
        assert!("0".parse::<UnitList>().is_err());
        assert!("248".parse::<UnitList>().is_err());
        assert!("5-2".parse::<UnitList>().is_err());
    }

    mod props {
        use super::*;
        use proptest::prelude::*;

        proptest! {
            /// Invariant of the give-up rule: units are tried in the list's order,
            /// each at most once; a setting that never gets a good frame costs at
            /// most `give_up` tries; once a frame has come, every unit of the list is
            /// tried.
            #[test]
            fn give_up_rule(
                n in 1usize..60,
                give_up in 1usize..10,
                answering in prop::collection::btree_set(1u8..60, 0..4),
                garbage in prop::collection::btree_set(1u8..60, 0..4),
            ) {
                let units: Vec<u8> = (1..=n as u8).collect();
                let mut at = AtSetting::new(units.clone(), give_up);
                let mut tried = Vec::new();
                while let Some(u) = at.next_unit() {
                    tried.push(u);
                    let heard = if answering.contains(&u) {
                        Heard::Frame { unit: u, pdu: vec![3, 2, 0, 0] }
                    } else if garbage.contains(&u) {
                        Heard::Garbage(3)
                    } else {
                        Heard::Nothing
                    };
                    at.record(&heard);
                    prop_assert!(tried.len() <= n);
                }
                prop_assert_eq!(&tried[..], &units[..tried.len()]);
                let first_answer = units.iter().position(|u| answering.contains(u));
                match first_answer {
                    Some(i) if i < give_up => prop_assert_eq!(tried.len(), n),
                    _ => prop_assert_eq!(tried.len(), give_up.min(n)),
                }
                prop_assert_eq!(at.left(), 0);
            }
        }
    }
}
