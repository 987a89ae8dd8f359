//! The silence mbgate leaves before each RTU request, timed on the device's side of a
//! pty: never less than the inter-frame gap (3.5 character times, Modbus over Serial
//! Line V1.02 §2.5.1.1, or `inter_frame_gap_us`). ASCII frames end with CR LF: no gap
//! is asked after a whole reply. The port is declared a wire (`port_kind = "wire"`):
//! on a pty left as one, nothing can collide and a request follows a whole reply at
//! once (docs/reliability.md "Knowing the wire"; the unit test
//! `no_gap_after_a_whole_reply_where_there_is_no_wire`).
//!
//! What a test can hold on any machine, however busy: the gateway never writes a
//! request before the gap has passed (a loaded machine only makes silences longer),
//! and the gap it asks its timer for is exactly the configured one (the unit tests of
//! `relay::line::serial`, with time passed in). How close to the gap the request then
//! leaves depends on how soon the kernel wakes the gateway: that is a figure for the
//! benchmark (`cargo bench --bench gateway -- rtu-limit`, docs/performance.md "RTU at
//! the line's limit"), not an assertion here.

use crate::common;
use common::sim::RawLine;
use common::*;
use mbgate::frame::{ascii, rtu};
use std::thread;
use std::time::{Duration, Instant};

/// Transactions a run times.
const N: usize = 40;

/// A device on the pty's far end answering `N` one-register reads, each once the
/// request can have reached it whole (its wire time after it was read), while a master
/// polls through the gateway as fast as it is answered. Returns the silence before
/// each request after the first: from the instant the device began writing the
/// previous reply (a pty delivers it at once) to the instant the request was read.
fn silences(baud: u32, serial: &[&str]) -> Vec<Duration> {
    silences_in("rtu", baud, serial)
}

/// [`silences`] in `framing` ("rtu" or "ascii").
fn silences_in(framing: &'static str, baud: u32, serial: &[&str]) -> Vec<Duration> {
    let encode: fn(u8, &[u8]) -> Vec<u8> = match framing {
        "rtu" => rtu::encode,
        _ => ascii::encode,
    };
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let mut dev = RawLine::open(&socat.dev);
    let device = thread::spawn(move || {
        let len = encode(1, &[0x03, 0, 0, 0, 1]).len();
        let request_time = wire_time(len, baud);
        let mut read_at = Vec::new();
        let mut replied_at = Vec::new();
        while read_at.len() < N {
            let req = dev.recv(len, Duration::from_secs(5));
            let at = Instant::now();
            assert_eq!(req.len(), len, "a whole request: {req:02X?}");
            let decoded = match framing {
                "rtu" => rtu::decode(&req).map(|(u, p)| (u, p.to_vec())),
                _ => ascii::decode(&req),
            };
            let (unit, pdu) = decoded.expect("a request with a good CRC or LRC");
            assert_eq!((unit, pdu[0]), (1, 0x03), "{req:02X?}");
            read_at.push(at);
            thread::sleep(request_time.saturating_sub(at.elapsed()));
            replied_at.push(Instant::now());
            dev.send(&encode(1, &[0x03, 2, 0, 7]));
        }
        (read_at, replied_at)
    });
    let mut cfg = Cfg::new(&socat.gw)
        .serial(&format!("framing = {framing:?}"))
        .serial("flow_control = \"none\"")
        .serial(&format!("baud_rate = {baud}"));
    for l in serial {
        cfg = cfg.serial(l);
    }
    let mut gw = Gateway::start(&cfg, dir.path());
    let mut m = gw.connect();
    for tid in 0..N as u16 {
        let reply = transact(&mut m, &read_req(tid, 1, 0, 1));
        assert_eq!(reply[7..], [0x03, 2, 0, 7], "{}", hexs(&reply));
    }
    let (read_at, replied_at) = device.join().unwrap();
    gw.stop();
    read_at[1..]
        .iter()
        .zip(&replied_at)
        .map(|(next, reply)| *next - *reply)
        .collect()
}

/// Every silence is at least `gap`: no request went out before the line had been quiet
/// that long after the reply. The silences are printed (median and all) for whoever
/// looks; their upper end is the machine's, not the gateway's, and is not asserted.
fn assert_silences(s: &[Duration], gap: Duration) {
    let mut sorted = s.to_vec();
    sorted.sort();
    let median = sorted[sorted.len() / 2];
    let shown: Vec<u128> = s.iter().map(|d| d.as_micros()).collect();
    eprintln!("gap {gap:?}: median silence {median:?}; all (µs): {shown:?}");
    assert!(
        sorted[0] >= gap,
        "a request {:?} after the reply, within the gap {gap:?}",
        sorted[0]
    );
}

/// The device's side paces its replies as a wire would: the gateway is told so.
const WIRE: &str = "port_kind = \"wire\"";

#[test]
fn silence_before_each_request_is_t35_at_115200_baud() {
    let s = silences(115_200, &[WIRE]);
    assert_silences(&s, Duration::from_micros(1750));
}

#[test]
fn silence_before_each_request_is_t35_at_9600_baud() {
    let s = silences(9600, &[WIRE]);
    // 3.5 characters of 10 bits at 9600 baud.
    assert_silences(&s, Duration::from_micros(3646));
}

#[test]
fn silence_before_each_request_follows_inter_frame_gap_us() {
    let s = silences(115_200, &["inter_frame_gap_us = 400"]);
    assert_silences(&s, Duration::from_micros(400));
}

/// ASCII: every request follows a whole reply and is answered (the gateway asks for no
/// gap after an ASCII reply, Modbus over Serial Line V1.02 §2.5.2.1; the unit tests of
/// `relay::line::serial` hold that to the microsecond).
#[test]
fn ascii_request_follows_a_whole_reply_without_a_gap() {
    let s = silences_in("ascii", 115_200, &[]);
    assert_eq!(s.len(), N - 1);
    assert_silences(&s, Duration::ZERO);
}
