//! The simulator's line model: bytes lost, garbage injected in
//! bursts and bytes replaced,
//! seeded so the same seed loses the same bytes, and the pace of a real UART, which a
//! pty does not have.

use std::time::{Duration, Instant};

/// Loss and noise in one direction. Each byte of the stream draws from the generator
/// in the same order whatever the chunking, so a seed fixes which bytes are hit.
#[derive(Debug, Clone)]
pub struct Faults {
    /// Chance that a byte is lost.
    pub(crate) drop: f64,
    /// Chance that a burst of 1 to 8 garbage bytes is inserted before a byte.
    pub(crate) noise: f64,
    /// Chance that a byte is replaced by another (a bit error).
    pub(crate) corrupt: f64,
    rng: fastrand::Rng,
    /// Bytes lost, inserted and replaced so far.
    pub(crate) dropped: u64,
    pub(crate) inserted: u64,
    pub(crate) corrupted: u64,
}

impl Faults {
    /// Faults that lose a byte with chance `drop` and insert garbage with chance
    /// `noise` (each 0.0..=1.0), drawn from a generator seeded with `seed`.
    pub fn new(drop: f64, noise: f64, seed: u64) -> Self {
        Self {
            drop,
            noise,
            corrupt: 0.0,
            rng: fastrand::Rng::with_seed(seed),
            dropped: 0,
            inserted: 0,
            corrupted: 0,
        }
    }

    /// Replaces bytes too, with probability `p` each.
    pub(crate) fn with_corrupt(mut self, p: f64) -> Self {
        self.corrupt = p;
        self
    }

    /// No faults at all.
    pub fn none() -> Self {
        Self::new(0.0, 0.0, 0)
    }

    pub(crate) fn is_active(&self) -> bool {
        self.drop > 0.0 || self.noise > 0.0 || self.corrupt > 0.0
    }

    /// Passes `bytes` through the faulty line, appending what comes out to `out`.
    pub fn apply(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        if !self.is_active() {
            out.extend_from_slice(bytes);
            return;
        }
        for &b in bytes {
            // Always three draws per byte (and more for garbage), so the stream of
            // decisions depends on the byte count alone.
            let noise = self.rng.f64() < self.noise;
            let lost = self.rng.f64() < self.drop;
            let corrupt = self.rng.f64() < self.corrupt;
            if noise {
                for _ in 0..self.rng.usize(1..=8) {
                    out.push(self.rng.u8(..));
                    self.inserted += 1;
                }
            }
            if lost {
                self.dropped += 1;
            } else if corrupt {
                out.push(b ^ self.rng.u8(1..));
                self.corrupted += 1;
            } else {
                out.push(b);
            }
        }
    }
}

/// One direction of a UART: when the byte now being sent will have left. Frames queue
/// behind each other at `char_time` a byte.
#[derive(Debug, Clone)]
pub(crate) struct Pacer {
    char_time: Duration,
    free_at: Option<Instant>,
}

impl Pacer {
    /// `baud` bits a second, `bits_per_char` bits a byte; `None` paces nothing.
    pub(crate) fn new(baud: Option<u32>, bits_per_char: u32) -> Self {
        let char_time = baud
            .filter(|&b| b > 0)
            .map(|b| Duration::from_nanos(u64::from(bits_per_char) * 1_000_000_000 / u64::from(b)))
            .unwrap_or_default();
        Self {
            char_time,
            free_at: None,
        }
    }

    pub(crate) fn char_time(&self) -> Duration {
        self.char_time
    }

    /// `bytes` ready to go at `ready`: the instant their last byte has left, after
    /// whatever is still being sent.
    pub(crate) fn finish(&mut self, ready: Instant, bytes: usize) -> Instant {
        let start = match self.free_at {
            Some(free) if free > ready => free,
            _ => ready,
        };
        let done = start + self.char_time * bytes as u32;
        self.free_at = Some(done);
        done
    }
}

/// How the simulator hands a frame to the line: whole, one byte
/// at a time, or in random bursts, with a gap before each piece after the first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum ChunkMode {
    Whole,
    Bytes,
    Random,
}

/// Splits frames into pieces and gaps, seeded.
#[derive(Debug, Clone)]
pub(crate) struct Chunker {
    mode: ChunkMode,
    gap: Duration,
    rng: fastrand::Rng,
}

impl Chunker {
    pub(crate) fn new(mode: ChunkMode, gap: Duration, seed: u64) -> Self {
        Self {
            mode,
            gap,
            rng: fastrand::Rng::with_seed(seed),
        }
    }

    /// The pieces of a `len`-byte frame: (bytes, gap before the piece).
    pub(crate) fn pieces(&mut self, len: usize) -> Vec<(usize, Duration)> {
        let mut out = Vec::new();
        let mut left = len;
        while left > 0 {
            let n = match self.mode {
                ChunkMode::Whole => left,
                ChunkMode::Bytes => 1,
                ChunkMode::Random => self.rng.usize(1..=left.min(8)),
            };
            let gap = match (out.is_empty(), self.mode) {
                (true, _) | (_, ChunkMode::Whole) => Duration::ZERO,
                (false, ChunkMode::Bytes) => self.gap,
                // Between half the gap and the whole of it.
                (false, ChunkMode::Random) => self.gap / 2 + self.gap.mul_f64(self.rng.f64() / 2.0),
            };
            out.push((n, gap));
            left -= n;
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(f: &mut Faults, chunks: &[&[u8]]) -> Vec<u8> {
        let mut out = Vec::new();
        for c in chunks {
            f.apply(c, &mut out);
        }
        out
    }

    #[test]
    fn same_seed_same_losses_at_any_chunking() {
        let data: Vec<u8> = (0..=255).cycle().take(10_000).collect();
        let a = run(&mut Faults::new(0.05, 0.01, 7), &[&data]);
        let (x, y) = data.split_at(3333);
        let b = run(&mut Faults::new(0.05, 0.01, 7), &[x, y]);
        assert_eq!(a, b);
        let c = run(&mut Faults::new(0.05, 0.01, 8), &[&data]);
        assert_ne!(a, c, "another seed, other bytes");
    }

    #[test]
    fn rates_are_what_was_asked() {
        let data = vec![0x55u8; 100_000];
        let mut f = Faults::new(0.01, 0.0, 1);
        let out = run(&mut f, &[&data]);
        assert_eq!(out.len() as u64 + f.dropped, 100_000);
        assert!(
            (800..1200).contains(&f.dropped),
            "about 1 % lost: {}",
            f.dropped
        );
        let mut f = Faults::new(0.0, 0.001, 1);
        let out = run(&mut f, &[&data]);
        assert_eq!(out.len() as u64, 100_000 + f.inserted);
        // About 100 bursts of 4.5 bytes.
        assert!((300..600).contains(&f.inserted), "bursts: {}", f.inserted);
        let mut f = Faults::new(0.0, 0.0, 1).with_corrupt(0.01);
        let out = run(&mut f, &[&data]);
        let changed = out.iter().filter(|&&b| b != 0x55).count() as u64;
        assert_eq!((out.len() as u64, changed), (100_000, f.corrupted));
        assert!(
            (800..1200).contains(&f.corrupted),
            "about 1 %: {}",
            f.corrupted
        );
    }

    #[test]
    fn no_faults_is_the_identity() {
        let mut f = Faults::none();
        assert_eq!(run(&mut f, &[b"abc", b"def"]), b"abcdef");
    }

    #[test]
    fn chunks_cover_the_frame_with_gaps_under_the_limit() {
        let gap = Duration::from_millis(40);
        let mut c = Chunker::new(ChunkMode::Random, gap, 3);
        for len in [1, 11, 260] {
            let p = c.pieces(len);
            assert_eq!(p.iter().map(|(n, _)| n).sum::<usize>(), len);
            assert_eq!(p[0].1, Duration::ZERO);
            assert!(p[1..]
                .iter()
                .all(|&(n, g)| (1..=8).contains(&n) && g >= gap / 2 && g <= gap));
        }
        let p = Chunker::new(ChunkMode::Bytes, gap, 0).pieces(3);
        assert_eq!(p, [(1, Duration::ZERO), (1, gap), (1, gap)]);
        assert_eq!(
            Chunker::new(ChunkMode::Whole, gap, 0).pieces(9),
            [(9, Duration::ZERO)]
        );
    }

    #[test]
    fn pacing_queues_frames_at_the_byte_rate() {
        // 19200 baud, 10 bits a byte: 520 833 ns a byte.
        let mut p = Pacer::new(Some(19_200), 10);
        assert_eq!(p.char_time(), Duration::from_nanos(520_833));
        let t0 = Instant::now();
        let first = p.finish(t0, 12);
        assert_eq!(first - t0, Duration::from_nanos(520_833 * 12));
        // Ready before the first has left: it waits its turn.
        let second = p.finish(t0, 12);
        assert_eq!(second - first, Duration::from_nanos(520_833 * 12));
        // Ready after the line went idle: starts at once.
        let later = second + Duration::from_millis(5);
        assert_eq!(p.finish(later, 1) - later, Duration::from_nanos(520_833));
        let mut none = Pacer::new(None, 10);
        assert_eq!(none.finish(t0, 100), t0);
    }
}
