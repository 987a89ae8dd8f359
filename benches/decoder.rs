//! Decoder benchmarks: the resynchronising serial decoder
//! ([`mbgate::frame::Resync`]) and the strict TCP decoder
//! ([`mbgate::frame::mbap::decode_strict`]) on clean streams and on streams that are
//! mostly garbage, at 1 MiB and 10 MiB, so the cost can be seen to grow linearly.
//!
//! `cargo bench --bench decoder` runs criterion, then prints a Markdown summary from
//! criterion's estimates (also written to `MBGATE_BENCH_MD` when set).

use bytes::BytesMut;
use criterion::{BenchmarkId, Criterion, Throughput};
use mbgate::frame::mbap::decode_strict;
use mbgate::frame::{Adu, ReplyJudge, Resync};
use std::fmt::Write as _;
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::time::Duration;

const MIB: usize = 1 << 20;
const SIZES: [(usize, &str); 2] = [(MIB, "1MiB"), (10 * MIB, "10MiB")];
/// What the relay reads from the port at a time.
const CHUNK: usize = 4096;

/// Replies of the shapes a CIE-M10 and a generic device send: FC 03 × 1, FC 03 × 10,
/// an FC 16 echo, an exception.
fn replies(tid: u16) -> Vec<Vec<u8>> {
    let regs: Vec<u8> = (0..20).collect();
    let mut r03 = vec![0x03, 20];
    r03.extend(&regs);
    [
        vec![0x03, 0x02, 0x00, 0xFF],
        r03,
        vec![0x10, 0x00, 0x08, 0x00, 0x01],
        vec![0x83, 0x02],
    ]
    .iter()
    .map(|pdu| Adu::build(tid, 1, pdu).as_bytes().to_vec())
    .collect()
}

/// The kinds of stream.
#[derive(Clone, Copy)]
enum Kind {
    /// Replies back to back.
    Clean,
    /// Nine bytes of random garbage to every byte of reply.
    Random,
    /// As much garbage, made of near misses: headers that look right (protocol id 0,
    /// a plausible length and function code) but announce up to 254 bytes that turn
    /// out to have the wrong shape, so the decoder waits, checks, and rescans.
    NearMiss,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Clean => "clean",
            Kind::Random => "garbage-random",
            Kind::NearMiss => "garbage-near-miss",
        }
    }
}

/// A stream of `size` bytes and the number of real frames in it.
fn stream(kind: Kind, size: usize) -> (Vec<u8>, usize) {
    let mut rng = fastrand::Rng::with_seed(5);
    let mut out = Vec::with_capacity(size + 512);
    let mut frames = 0;
    let mut tid = 0u16;
    while out.len() < size {
        tid = tid.wrapping_add(1);
        for f in replies(tid) {
            let garbage = match kind {
                Kind::Clean => 0,
                _ => 9 * f.len(),
            };
            let end = out.len() + garbage;
            while out.len() < end {
                match kind {
                    Kind::NearMiss => {
                        // A header for a long FC 03 reply whose byte count is wrong.
                        let len = rng.u8(100..=254);
                        out.extend([rng.u8(..), rng.u8(..), 0, 0, 0, len, 1, 0x03, 0]);
                    }
                    _ => out.push(rng.u8(..)),
                }
            }
            out.truncate(end);
            out.extend(&f);
            frames += 1;
        }
    }
    (out, frames)
}

/// Feeds the stream to a fresh serial decoder a read at a time, as the relay does,
/// then declares the line quiet; returns the frames found.
fn serial_decode(bytes: &[u8]) -> usize {
    let mut d = Resync::new();
    let mut n = 0;
    for chunk in bytes.chunks(CHUNK) {
        d.push(chunk);
        while d.next_frame(&ReplyJudge, false).is_some() {
            n += 1;
        }
    }
    while d.next_frame(&ReplyJudge, true).is_some() {
        n += 1;
    }
    n
}

/// Feeds a stream of requests to the strict TCP decoder a read at a time, as a
/// connection does; returns the frames found.
fn tcp_decode(bytes: &[u8]) -> usize {
    let mut buf = BytesMut::with_capacity(CHUNK);
    let mut n = 0;
    for chunk in bytes.chunks(CHUNK) {
        buf.extend_from_slice(chunk);
        while let Ok(Some(_)) = decode_strict(&mut buf) {
            n += 1;
        }
    }
    n
}

/// Pipelined FC 03 requests, `size` bytes of them.
fn requests(size: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(size + 12);
    let mut tid = 0u16;
    while out.len() < size {
        tid = tid.wrapping_add(1);
        out.extend(Adu::build(tid, 1, &[0x03, 0, 0, 0, 10]).as_bytes());
    }
    out
}

fn benches(c: &mut Criterion) {
    let mut g = c.benchmark_group("serial");
    g.sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(3));
    for kind in [Kind::Clean, Kind::Random, Kind::NearMiss] {
        for (size, label) in SIZES {
            let (bytes, _) = stream(kind, size);
            g.throughput(Throughput::Bytes(bytes.len() as u64));
            g.bench_with_input(BenchmarkId::new(kind.name(), label), &bytes, |b, s| {
                b.iter(|| serial_decode(black_box(s)))
            });
        }
    }
    g.finish();
    let mut g = c.benchmark_group("tcp");
    g.sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(3));
    for (size, label) in SIZES {
        let bytes = requests(size);
        g.throughput(Throughput::Bytes(bytes.len() as u64));
        g.bench_with_input(BenchmarkId::new("clean", label), &bytes, |b, s| {
            b.iter(|| tcp_decode(black_box(s)))
        });
    }
    g.finish();
}

/// Where criterion keeps its estimates: `$CRITERION_HOME`, else the target directory's
/// `criterion`. Set here so criterion and the summary agree.
fn criterion_home() -> PathBuf {
    let home = std::env::var_os("CRITERION_HOME")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            std::env::var_os("CARGO_TARGET_DIR")
                .map(PathBuf::from)
                .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("target"))
                .join("criterion")
        });
    std::env::set_var("CRITERION_HOME", &home);
    home
}

/// Criterion's mean time of one benchmark, in seconds.
fn mean_seconds(home: &Path, id: &str) -> Option<f64> {
    let path = home.join(id).join("new/estimates.json");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()?;
    Some(json["mean"]["point_estimate"].as_f64()? / 1e9)
}

fn summary(home: &Path) -> String {
    let mut s = String::from(
        "| decoder | stream | size | frames found / in it | mean time | throughput |\n|---|---|---|---|---|---|\n",
    );
    let mut lin = String::from(
        "| decoder | stream | time 10 MiB / time 1 MiB | linear (8..12)? |\n|---|---|---|---|\n",
    );
    let cases: Vec<(&str, Kind)> = vec![
        ("serial", Kind::Clean),
        ("serial", Kind::Random),
        ("serial", Kind::NearMiss),
        ("tcp", Kind::Clean),
    ];
    for (decoder, kind) in cases {
        let mut times = Vec::new();
        for (size, label) in SIZES {
            let (bytes, frames, found) = if decoder == "tcp" {
                let b = requests(size);
                let n = b.len() / 12;
                let found = tcp_decode(&b);
                (b, n, found)
            } else {
                let (b, n) = stream(kind, size);
                let found = serial_decode(&b);
                (b, n, found)
            };
            let t = mean_seconds(home, &format!("{decoder}/{}/{label}", kind.name()));
            times.push(t);
            let (time, rate) = match t {
                Some(t) => (
                    format!("{:.2} ms", t * 1e3),
                    format!("{:.0} MiB/s", bytes.len() as f64 / MIB as f64 / t),
                ),
                None => ("n/a".into(), "n/a".into()),
            };
            let _ = writeln!(
                s,
                "| {decoder} | {} | {label} | {found} / {frames} | {time} | {rate} |",
                kind.name()
            );
        }
        if let [Some(a), Some(b)] = times[..] {
            let r = b / a;
            let ok = if (8.0..=12.0).contains(&r) {
                "yes"
            } else {
                "**no**"
            };
            let _ = writeln!(lin, "| {decoder} | {} | {r:.2} | {ok} |", kind.name());
        }
    }
    format!(
        "Streams are fed {CHUNK} bytes at a time, as the gateway reads them. Garbage streams hold nine bytes of garbage to every byte of frame (90 %).\n\n{s}\n{lin}"
    )
}

fn main() {
    let home = criterion_home();
    let benchmarking = std::env::args().any(|a| a == "--bench");
    let mut c = Criterion::default().configure_from_args();
    benches(&mut c);
    c.final_summary();
    if benchmarking {
        let md = summary(&home);
        println!("\n{md}");
        if let Some(path) = std::env::var_os("MBGATE_BENCH_MD") {
            std::fs::write(&path, &md).expect("write MBGATE_BENCH_MD");
        }
    }
}
