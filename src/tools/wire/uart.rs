//! The virtual line's wire, pure: how a character is framed in bits (start, data,
//! parity, stop), how long it takes at a baud rate, and how a UART at its own baud rate
//! and format samples the line it hears, so that bytes sent at another rate arrive
//! garbled, with parity and framing errors, as a real receiver would take them.
//! Times are nanoseconds on the caller's timeline; nothing here reads a clock.

use std::collections::VecDeque;

/// Nanoseconds in a second: bit times are kept as `NS / baud`, exactly, by integer
/// arithmetic on the product, so 1000 characters add no rounding.
const NS: u64 = 1_000_000_000;

/// A character's parity bit (Modbus over Serial Line V1.02 §2.5.1: even by default,
/// none with two stop bits allowed).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Parity {
    /// No parity bit.
    None,
    /// The bit makes the count of ones even.
    Even,
    /// The bit makes the count of ones odd.
    Odd,
}

/// How a character is framed: data bits, parity, stop bits (`8E1`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Format {
    /// 5 to 8.
    pub(crate) data_bits: u8,
    /// The parity bit, if any.
    pub(crate) parity: Parity,
    /// 1 or 2.
    pub(crate) stop_bits: u8,
}

impl Format {
    /// 8 data bits, no parity, 1 stop bit.
    pub(crate) const N81: Format = Format {
        data_bits: 8,
        parity: Parity::None,
        stop_bits: 1,
    };

    /// Bits on the wire per character: start, data, parity, stop.
    pub(crate) fn bits(self) -> u32 {
        1 + u32::from(self.data_bits)
            + u32::from(self.parity != Parity::None)
            + u32::from(self.stop_bits)
    }
}

/// A character format that is not one.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0:?}: expected a format like 8N1, 8E1, 8O1 or 8N2")]
pub(crate) struct BadFormat(String);

impl std::str::FromStr for Format {
    type Err = BadFormat;

    /// `8N1`, `8E1`, `7O2`...: data bits 5 to 8, parity N, E or O, stop bits 1 or 2.
    fn from_str(s: &str) -> Result<Format, BadFormat> {
        let bad = || BadFormat(s.to_owned());
        let b = s.as_bytes();
        if b.len() != 3 {
            return Err(bad());
        }
        let data_bits = match b[0] {
            d @ b'5'..=b'8' => d - b'0',
            _ => return Err(bad()),
        };
        let parity = match b[1].to_ascii_uppercase() {
            b'N' => Parity::None,
            b'E' => Parity::Even,
            b'O' => Parity::Odd,
            _ => return Err(bad()),
        };
        let stop_bits = match b[2] {
            b'1' => 1,
            b'2' => 2,
            _ => return Err(bad()),
        };
        Ok(Format {
            data_bits,
            parity,
            stop_bits,
        })
    }
}

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let p = match self.parity {
            Parity::None => 'N',
            Parity::Even => 'E',
            Parity::Odd => 'O',
        };
        write!(f, "{}{p}{}", self.data_bits, self.stop_bits)
    }
}

/// One end's UART: its baud rate and format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct UartSetting {
    /// Bits per second (above 0).
    pub(crate) baud: u32,
    /// How it frames a character.
    pub(crate) format: Format,
}

impl UartSetting {
    /// A character's time on the wire, in nanoseconds, rounded up.
    pub(crate) fn char_ns(self) -> u64 {
        after_bits(self.format.bits(), self.baud)
    }
}

/// Nanoseconds from a character's start to the start of its bit `i` at `baud`
/// (rounded up: the instant the line is at that bit).
fn after_bits(i: u32, baud: u32) -> u64 {
    (u64::from(i) * NS).div_ceil(u64::from(baud.max(1)))
}

/// The levels of a character's bits as they go out, first bit in bit 0: the start bit
/// (0), the data bits least significant first, the parity bit, the stop bits (1).
pub(crate) fn frame(byte: u8, format: Format) -> u16 {
    let data_mask = (1u16 << format.data_bits) - 1;
    let data = u16::from(byte) & data_mask;
    let mut bits = data << 1;
    let mut n = 1 + u32::from(format.data_bits);
    match format.parity {
        Parity::None => {}
        p => {
            let ones = data.count_ones();
            let bit = match p {
                Parity::Even => ones % 2,
                _ => 1 - ones % 2,
            };
            bits |= (bit as u16) << n;
            n += 1;
        }
    }
    for _ in 0..format.stop_bits {
        bits |= 1 << n;
        n += 1;
    }
    bits
}

/// A character on the line: when its start bit begins, how fast its bits go, their
/// levels ([`frame`]) and how many there are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Char {
    /// When the start bit begins.
    pub(crate) start: u64,
    /// The sender's baud rate.
    pub(crate) baud: u32,
    /// The levels, first bit in bit 0.
    pub(crate) bits: u16,
    /// How many bits.
    pub(crate) len: u32,
}

impl Char {
    /// `byte` sent at `setting` from `start`.
    pub(crate) fn new(start: u64, byte: u8, setting: UartSetting) -> Char {
        Char {
            start,
            baud: setting.baud,
            bits: frame(byte, setting.format),
            len: setting.format.bits(),
        }
    }

    /// When its last stop bit ends.
    pub(crate) fn end(&self) -> u64 {
        self.start + after_bits(self.len, self.baud)
    }

    /// Its level at `t` (idle, 1, outside it).
    fn level(&self, t: u64) -> bool {
        if t < self.start || t >= self.end() {
            return true;
        }
        let i = (t - self.start) * u64::from(self.baud) / NS;
        self.bits >> i & 1 == 1
    }

    /// The first instant at or after `from` it holds the line low, if any.
    fn first_low(&self, from: u64) -> Option<u64> {
        (0..self.len)
            .filter(|i| self.bits >> i & 1 == 0)
            .map(|i| {
                (
                    self.start + after_bits(i, self.baud),
                    self.start + after_bits(i + 1, self.baud),
                )
            })
            .find(|&(_, end)| end > from)
            .map(|(begin, _)| begin.max(from))
    }
}

/// What a UART made of a character it sampled.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Sampled {
    /// A good character.
    Byte(u8),
    /// Its parity bit was wrong: the data bits as sampled.
    Parity(u8),
    /// Its stop bit was low: the data bits as sampled.
    Framing(u8),
    /// All of it low, stop bit included (a break, or a much slower sender's zeros).
    Break,
}

/// What the receiving program's termios asks done with a bad character
/// (termios(3): IGNPAR, INPCK, PARMRK; IGNBRK), as Linux's 8250 driver and line
/// discipline do it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) struct ErrorHandling {
    /// IGNPAR: characters with parity or framing errors are dropped.
    pub(crate) ignore: bool,
    /// INPCK: parity checked; a bad character reads as 0 (or marked, with PARMRK).
    pub(crate) check: bool,
    /// PARMRK: a bad character reads as 0xFF 0x00 and itself.
    pub(crate) mark: bool,
    /// IGNBRK: a break is dropped.
    pub(crate) ignore_break: bool,
}

impl ErrorHandling {
    /// The bytes the program reads for `r`.
    pub(crate) fn deliver(self, r: Sampled, out: &mut Vec<u8>) {
        match r {
            Sampled::Byte(b) => out.push(b),
            Sampled::Parity(b) | Sampled::Framing(b) => {
                if self.ignore {
                } else if self.check && self.mark {
                    out.extend_from_slice(&[0xFF, 0x00, b]);
                } else if self.check {
                    out.push(0);
                } else {
                    out.push(b);
                }
            }
            Sampled::Break => {
                if self.ignore_break {
                } else if self.mark {
                    out.extend_from_slice(&[0xFF, 0x00, 0x00]);
                } else {
                    out.push(0);
                }
            }
        }
    }
}

/// One end's receiver and the line it hears: the characters sent towards it (by the
/// other end, and by itself where the line echoes), their levels ANDed where they
/// overlap (a collision: either sender's low wins), sampled as a UART does: a start
/// bit found where the line is low (checked again half a bit later), each further bit
/// sampled in its middle, the next start searched from the middle of the stop bit.
#[derive(Debug, Default)]
pub(crate) struct UartReceiver {
    /// Characters on the line, ordered by start.
    chars: VecDeque<Char>,
    /// Where the search for the next start bit begins.
    cursor: u64,
}

/// What [`Receiver::poll`] found due.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Arrival {
    /// When the receiver had the character: the end of its own last stop bit.
    pub(crate) at: u64,
    /// What it made of it.
    pub(crate) what: Sampled,
}

impl UartReceiver {
    /// A receiver on an idle line.
    pub(crate) fn new() -> UartReceiver {
        UartReceiver::default()
    }

    /// A character put on the line. Characters come in order of start, each starting
    /// no earlier than the instant it is pushed at (the caller's "now"), which is what
    /// lets [`poll`](Self::poll) take the line as known up to now.
    pub(crate) fn push(&mut self, c: Char) {
        let at = self.chars.partition_point(|k| k.start <= c.start);
        self.chars.insert(at, c);
    }

    fn level(&self, t: u64) -> bool {
        self.chars
            .iter()
            .take_while(|c| c.start <= t)
            .all(|c| c.level(t))
    }

    /// The first instant at or after `from` the line is low. Characters are ordered by
    /// start, so the search ends at the first one that starts after the best found
    /// (a long queue costs a few characters per call, not all of them).
    fn first_low(&self, from: u64) -> Option<u64> {
        let mut best: Option<u64> = None;
        for c in &self.chars {
            if best.is_some_and(|b| c.start >= b) {
                break;
            }
            if let Some(t) = c.first_low(from) {
                best = Some(best.map_or(t, |b| b.min(t)));
            }
        }
        best
    }

    /// The character whose start bit falls at `t0`, sampled at the middle of each bit;
    /// and the middle of its stop bit, where the search for the next one starts.
    fn sample(&self, t0: u64, setting: UartSetting) -> (Sampled, u64) {
        let f = setting.format;
        let baud = setting.baud;
        let mid = |t0: u64, i: u32| t0 + (u64::from(2 * i + 1) * NS).div_ceil(2 * u64::from(baud));
        let mut data = 0u8;
        let mut ones = 0;
        for i in 0..u32::from(f.data_bits) {
            if self.level(mid(t0, 1 + i)) {
                data |= 1 << i;
                ones += 1;
            }
        }
        let mut next = 1 + u32::from(f.data_bits);
        let mut parity_ok = true;
        let mut parity_bit = false;
        if f.parity != Parity::None {
            parity_bit = self.level(mid(t0, next));
            let total = ones + u32::from(parity_bit);
            parity_ok = match f.parity {
                Parity::Even => total % 2 == 0,
                _ => total % 2 == 1,
            };
            next += 1;
        }
        let stop = self.level(mid(t0, next));
        let what = if !stop && data == 0 && !parity_bit {
            Sampled::Break
        } else if !stop {
            Sampled::Framing(data)
        } else if !parity_ok {
            Sampled::Parity(data)
        } else {
            Sampled::Byte(data)
        };
        (what, mid(t0, next))
    }

    /// The characters the receiver has taken by `now`, in order, and when the next
    /// may be due (none while the line stays idle). `now` must not go back.
    pub(crate) fn poll(&mut self, now: u64, setting: UartSetting) -> (Vec<Arrival>, Option<u64>) {
        let mut out = Vec::new();
        let baud = setting.baud;
        // The middle of bit `i` of a character starting at `t0`.
        let mid = |t0: u64, i: u32| t0 + (u64::from(2 * i + 1) * NS).div_ceil(2 * u64::from(baud));
        let wake = loop {
            let Some(t0) = self.first_low(self.cursor) else {
                break None;
            };
            let done = t0 + setting.char_ns();
            if done > now {
                break Some(done);
            }
            if self.level(mid(t0, 0)) {
                // A glitch, not a start bit: search on from half a bit later.
                self.cursor = mid(t0, 0);
                continue;
            }
            let (what, end) = self.sample(t0, setting);
            out.push(Arrival { at: done, what });
            self.cursor = end;
            let cursor = self.cursor;
            while self.chars.front().is_some_and(|c| c.end() <= cursor) {
                self.chars.pop_front();
            }
        };
        if wake.is_none() {
            // Nothing low ahead: what has ended is done with.
            let cursor = self.cursor;
            self.chars.retain(|c| c.end() > cursor);
        }
        (out, wake)
    }
}

/// One end's transmitter: characters go back to back while it has them, each after the
/// one before, never before it was written.
#[derive(Debug, Default)]
pub(crate) struct UartTransmitter {
    free_at: u64,
}

impl UartTransmitter {
    /// When the characters of `count` bytes written at `now` start, at `setting`.
    pub(crate) fn schedule(&mut self, now: u64, count: usize, setting: UartSetting) -> Vec<u64> {
        let first = now.max(self.free_at);
        let starts: Vec<u64> = (0..count as u64)
            .map(|i| first + after_bits((i as u32) * setting.format.bits(), setting.baud))
            .collect();
        self.free_at = first + after_bits(count as u32 * setting.format.bits(), setting.baud);
        starts
    }

    /// When the last character written so far has left.
    #[cfg(test)]
    pub(crate) fn free_at(&self) -> u64 {
        self.free_at
    }
}

/// What the line does to a character on its way: lost (the receiver hears an idle
/// line), or one of its bits flipped (noise: any bit, the start and stop bits included),
/// each with its probability, drawn from `rng` (seeded: a run can be repeated).
pub(crate) fn disturb(c: Char, loss: f64, noise: f64, rng: &mut fastrand::Rng) -> Option<Char> {
    if loss > 0.0 && rng.f64() < loss {
        return None;
    }
    let mut c = c;
    if noise > 0.0 && rng.f64() < noise {
        c.bits ^= 1 << rng.u32(0..c.len);
    }
    Some(c)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(baud: u32, f: &str) -> UartSetting {
        UartSetting {
            baud,
            format: f.parse().unwrap(),
        }
    }

    /// Sends `bytes` back to back from 0 at `tx` and returns what a receiver at `rx`
    /// makes of them once all is over.
    fn across(bytes: &[u8], tx: UartSetting, rx: UartSetting) -> Vec<Sampled> {
        let mut t = UartTransmitter::default();
        let mut r = UartReceiver::new();
        for (b, start) in bytes.iter().zip(t.schedule(0, bytes.len(), tx)) {
            r.push(Char::new(start, *b, tx));
        }
        let (got, wake) = r.poll(u64::MAX / 2, rx);
        assert_eq!(wake, None);
        got.into_iter().map(|a| a.what).collect()
    }

    #[test]
    fn formats_parse_count_and_print() {
        let f: Format = "8E1".parse().unwrap();
        assert_eq!(f.bits(), 11);
        assert_eq!(f.to_string(), "8E1");
        assert_eq!("8N1".parse::<Format>().unwrap().bits(), 10);
        assert_eq!("7o2".parse::<Format>().unwrap().bits(), 11);
        assert!("9N1".parse::<Format>().is_err());
        assert!("8X1".parse::<Format>().is_err());
        assert!("8N3".parse::<Format>().is_err());
    }

    #[test]
    fn frames_have_start_data_parity_stop() {
        // 0x01 8N1: start 0, data 1 then seven 0s, stop 1.
        assert_eq!(frame(0x01, Format::N81), 0b10_0000_0010);
        // 0x03 8E1: two ones, even parity bit 0.
        assert_eq!(frame(0x03, "8E1".parse().unwrap()), 0b100_0000_0110);
        // 0x03 8O1: the parity bit 1.
        assert_eq!(frame(0x03, "8O1".parse().unwrap()), 0b110_0000_0110);
    }

    #[test]
    fn a_byte_takes_its_bits_time() {
        // 10 bits at 9600: 1.0417 ms; 11 at 19200: 572.9 µs.
        assert_eq!(s(9600, "8N1").char_ns(), 1_041_667);
        assert_eq!(s(19200, "8E1").char_ns(), 572_917);
        // 1000 bytes back to back: 1.0417 s, no rounding added per byte.
        let mut t = UartTransmitter::default();
        let starts = t.schedule(0, 1000, s(9600, "8N1"));
        assert_eq!(starts[1], 1_041_667);
        assert_eq!(t.free_at(), 1_041_666_667);
        // Written later than the line frees: starts when written.
        let later = t.schedule(2_000_000_000, 1, s(9600, "8N1"));
        assert_eq!(later, vec![2_000_000_000]);
        // Written while busy: queued after.
        let queued = t.schedule(2_000_000_001, 1, s(9600, "8N1"));
        assert_eq!(queued, vec![2_001_041_667]);
    }

    #[test]
    fn same_setting_delivers_every_byte_at_its_end() {
        for f in ["8N1", "8E1", "8O1", "8N2", "7E1"] {
            let set = s(9600, f);
            let bytes: Vec<u8> = (0..=255u8)
                .map(|b| {
                    if set.format.data_bits == 7 {
                        b & 0x7F
                    } else {
                        b
                    }
                })
                .collect();
            let got = across(&bytes, set, set);
            let want: Vec<Sampled> = bytes.iter().map(|&b| Sampled::Byte(b)).collect();
            assert_eq!(got, want, "{f}");
        }
        let mut r = UartReceiver::new();
        r.push(Char::new(0, 0x55, s(9600, "8N1")));
        // Not before its last stop bit has ended.
        let (early, wake) = r.poll(1_041_666, s(9600, "8N1"));
        assert!(early.is_empty());
        assert_eq!(wake, Some(1_041_667));
        let (got, wake) = r.poll(1_041_667, s(9600, "8N1"));
        assert_eq!(
            got,
            vec![Arrival {
                at: 1_041_667,
                what: Sampled::Byte(0x55)
            }]
        );
        assert_eq!(wake, None);
    }

    #[test]
    fn other_baud_rates_garble() {
        // A Modbus RTU request at 19200 heard at 9600, and the other way round:
        // never the bytes that were sent.
        let req = [0x01, 0x03, 0x00, 0x00, 0x00, 0x01, 0x84, 0x0A];
        for (tx, rx) in [(19200, 9600), (9600, 19200), (9600, 115200), (115200, 9600)] {
            let got = across(&req, s(tx, "8N1"), s(rx, "8N1"));
            let clean: Vec<Sampled> = req.iter().map(|&b| Sampled::Byte(b)).collect();
            assert_ne!(got, clean, "{tx} -> {rx}");
        }
        // Twice as slow a receiver hears a 0x00 at 19200 as 4.5 of its bits low (start
        // and 8 data bits), then high: its data bits 0 to 2, sampled at 1.5, 2.5 and 3.5
        // bits, low, bit 3 (at 4.5, where the stop bit begins) and on high: 0xF8.
        assert_eq!(
            across(&[0x00], s(19200, "8N1"), s(9600, "8N1")),
            vec![Sampled::Byte(0xF8)]
        );
        // A much slower sender's 0x00 holds the line low past the faster receiver's
        // stop bit: a break.
        assert_eq!(
            across(&[0x00], s(1200, "8N1"), s(9600, "8N1"))[0],
            Sampled::Break
        );
        // Same baud, the receiver expecting a parity bit where a stop bit comes: a
        // lone 0x00 has its stop bit read as a parity 1 (odd count: wrong); back to
        // back, the next start bit lands on its stop bit, a framing error.
        assert_eq!(
            across(&[0x00], s(9600, "8N1"), s(9600, "8E1")),
            vec![Sampled::Parity(0x00)]
        );
        assert_eq!(
            across(&[0x00, 0x00], s(9600, "8N1"), s(9600, "8E1"))[0],
            Sampled::Framing(0x00)
        );
    }

    #[test]
    fn collisions_and_echo_share_the_line() {
        // Two senders at once: the lows win, the receiver gets the AND.
        let set = s(9600, "8N1");
        let mut r = UartReceiver::new();
        r.push(Char::new(0, 0xF0, set));
        r.push(Char::new(0, 0x0F, set));
        let (got, _) = r.poll(u64::MAX / 2, set);
        assert_eq!(got[0].what, Sampled::Byte(0x00));
    }

    #[test]
    fn error_handling_follows_termios() {
        let mut out = Vec::new();
        let raw = ErrorHandling::default();
        raw.deliver(Sampled::Parity(0x41), &mut out);
        raw.deliver(Sampled::Break, &mut out);
        assert_eq!(out, vec![0x41, 0x00]);
        out.clear();
        let checked = ErrorHandling {
            check: true,
            ..ErrorHandling::default()
        };
        checked.deliver(Sampled::Framing(0x41), &mut out);
        assert_eq!(out, vec![0x00]);
        out.clear();
        let ignored = ErrorHandling {
            ignore: true,
            ignore_break: true,
            ..ErrorHandling::default()
        };
        ignored.deliver(Sampled::Parity(0x41), &mut out);
        ignored.deliver(Sampled::Break, &mut out);
        ignored.deliver(Sampled::Byte(0x42), &mut out);
        assert_eq!(out, vec![0x42]);
        out.clear();
        let marked = ErrorHandling {
            check: true,
            mark: true,
            ..ErrorHandling::default()
        };
        marked.deliver(Sampled::Parity(0x41), &mut out);
        assert_eq!(out, vec![0xFF, 0x00, 0x41]);
    }

    #[test]
    fn loss_and_noise_rates_are_what_was_asked() {
        let set = s(9600, "8N1");
        let mut rng = fastrand::Rng::with_seed(7);
        let n = 20_000;
        let mut lost = 0;
        let mut flipped = 0;
        for i in 0..n {
            let c = Char::new(i * 2_000_000, 0x55, set);
            match disturb(c, 0.1, 0.05, &mut rng) {
                None => lost += 1,
                Some(d) if d != c => flipped += 1,
                Some(_) => {}
            }
        }
        // 10 % of 20 000 is 2000, standard deviation 42; 5 % of the 18 000 kept is 900,
        // deviation 29: five deviations either side.
        assert!((1790..=2210).contains(&lost), "{lost} lost");
        assert!((755..=1045).contains(&flipped), "{flipped} flipped");
        // No rates: nothing touched.
        let c = Char::new(0, 0x55, set);
        assert_eq!(disturb(c, 0.0, 0.0, &mut rng), Some(c));
    }

    #[test]
    fn a_flipped_bit_is_a_wrong_byte_or_an_error() {
        let set = s(9600, "8E1");
        let mut c = Char::new(0, 0x55, set);
        c.bits ^= 1 << 3; // a data bit: parity catches it
        let mut r = UartReceiver::new();
        r.push(c);
        let (got, _) = r.poll(u64::MAX / 2, set);
        assert_eq!(got[0].what, Sampled::Parity(0x55 ^ 0x04));
    }

    mod props {
        use super::*;
        use proptest::prelude::*;

        fn format() -> impl Strategy<Value = Format> {
            prop_oneof![
                Just("8N1"),
                Just("8E1"),
                Just("8O1"),
                Just("8N2"),
                Just("7E1")
            ]
            .prop_map(|f| f.parse().unwrap())
        }

        proptest! {
            /// Invariant: at one setting, whatever the bytes and however they are
            /// written (bursts with pauses of any length, polled at any instants),
            /// the receiver gets exactly the bytes, in order, each at the end of its
            /// own character, never before.
            #[test]
            fn same_setting_is_the_identity(
                bursts in prop::collection::vec(
                    (prop::collection::vec(any::<u8>(), 1..20), 0u64..5_000_000),
                    1..6,
                ),
                baud in prop_oneof![Just(1200u32), Just(9600), Just(19200), Just(115200)],
                f in format(),
                polls in prop::collection::vec(0u64..3_000_000, 0..20),
            ) {
                let set = UartSetting { baud, format: f };
                let mask = if f.data_bits == 7 { 0x7F } else { 0xFF };
                let mut t = UartTransmitter::default();
                let mut r = UartReceiver::new();
                let mut now = 0;
                let mut sent = Vec::new();
                let mut ends = Vec::new();
                let mut got = Vec::new();
                let mut poll_at = polls.into_iter();
                for (bytes, pause) in bursts {
                    now += pause;
                    for (b, start) in bytes.iter().zip(t.schedule(now, bytes.len(), set)) {
                        let c = Char::new(start, *b, set);
                        ends.push(c.end());
                        r.push(c);
                        sent.push(b & mask);
                    }
                    if let Some(p) = poll_at.next() {
                        now += p;
                        got.extend(r.poll(now, set).0);
                    }
                }
                got.extend(r.poll(u64::MAX / 2, set).0);
                let bytes: Vec<Sampled> = sent.iter().map(|&b| Sampled::Byte(b)).collect();
                prop_assert_eq!(got.iter().map(|a| a.what).collect::<Vec<_>>(), bytes);
                for (a, end) in got.iter().zip(ends) {
                    prop_assert_eq!(a.at, end);
                }
            }

            /// Invariant: at any two settings, what the receiver takes comes in order
            /// of time, each no earlier than a whole character of its own after the
            /// first byte sent began, and it takes no more characters than the line's
            /// busy time could hold at its own rate.
            #[test]
            fn any_mismatch_arrives_in_order_and_bounded(
                bytes in prop::collection::vec(any::<u8>(), 1..40),
                tx_baud in prop_oneof![Just(1200u32), Just(9600), Just(19200), Just(115200)],
                rx_baud in prop_oneof![Just(1200u32), Just(9600), Just(19200), Just(115200)],
                tx_f in format(),
                rx_f in format(),
            ) {
                let tx = UartSetting { baud: tx_baud, format: tx_f };
                let rx = UartSetting { baud: rx_baud, format: rx_f };
                let mut t = UartTransmitter::default();
                let mut r = UartReceiver::new();
                for (b, start) in bytes.iter().zip(t.schedule(0, bytes.len(), tx)) {
                    r.push(Char::new(start, *b, tx));
                }
                let (got, wake) = r.poll(u64::MAX / 2, rx);
                prop_assert_eq!(wake, None);
                let busy = t.free_at();
                // A start bit needs a low level, found within the busy time; each
                // character takes at least its stop-bit middle before the next.
                let most = (busy / (rx.char_ns() / u64::from(rx.format.bits()) * u64::from(1 + u32::from(rx.format.data_bits)))) + 1;
                prop_assert!(got.len() as u64 <= most, "{} > {}", got.len(), most);
                let mut last = 0;
                for a in &got {
                    prop_assert!(a.at >= last);
                    prop_assert!(a.at >= rx.char_ns());
                    last = a.at;
                }
            }
        }
    }
}
