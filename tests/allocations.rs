//! No allocation a transaction: the gateway in this process, counted by a global
//! allocator of the test's own (a binary of its own: one allocator a process), with
//! one master polling through it (an MBAP line and an RTU line, each a simulated
//! device on a pty of its own). Once warm (every buffer at
//! the size it keeps, every table holding what it holds), a transaction allocates
//! nothing: not its request's place in the queue, not the frame for the line, not the
//! reply for the master (docs/performance.md "A transaction on a quiet line").

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::process::Stdio;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Duration;

/// Every allocation in the process (every thread: the gateway's runtime and whatever
/// it starts), counted. The simulator is a process of its own.
struct Counting;

static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

// SAFETY: every call is passed on to the system allocator as it came; the count is a
// relaxed atomic, which allocates nothing.
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: the caller's contract, passed on.
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: the caller's contract, passed on.
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: the caller's contract, passed on.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: the caller's contract, passed on.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static COUNTING: Counting = Counting;

/// One gateway at a time: the count is the whole process's.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

/// Warm-up: more than enough for every kept buffer to reach its size (the line's
/// retired ids, 1024, are the longest).
const WARM: u16 = 1500;
const COUNTED: u16 = 2000;

/// The allocations of `COUNTED` transactions, FC 03 × 1 of unit 1, through a gateway in
/// this process whose line is `framing`, to a simulated device on a pty.
fn allocations_a_run(framing: &str) -> u64 {
    let dir = common::tempdir();
    let link = dir.path().join("line");
    let link_s = link.to_str().unwrap();
    // Its output goes nowhere: reading it here would allocate in this process.
    let mut sim = std::process::Command::new(env!("CARGO_BIN_EXE_mbgate"))
        .args(["sim", "--pty", link_s, "--framing", framing])
        .args(["--profile", "generic", "--units", "1", "--headless"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    common::wait_for("the simulator's pty", Duration::from_secs(20), || {
        link.exists()
    });
    let port = common::free_port();
    let flow = if framing == "mbap" {
        "hardware"
    } else {
        "none"
    };
    let toml = format!(
        "[serial]\npath = {link_s:?}\nframing = {framing:?}\nflow_control = {flow:?}\n\
         [tcp]\nlisten = \"127.0.0.1:{port}\"\n[log]\nlevel = \"warn\"\n"
    );
    let file = dir.path().join("gw.toml");
    std::fs::write(&file, toml).unwrap();
    let cfg = mbgate::config::load(&file).unwrap();
    let shutdown = tokio_util::sync::CancellationToken::new();
    let stop = shutdown.clone();
    let gateway = std::thread::spawn(move || {
        let rt = mbgate::cli::runtime::new().unwrap();
        rt.block_on(mbgate::gateway::run(cfg, stop)).map(|_| ())
    });
    let mut master = None;
    common::wait_for("the gateway's listener", Duration::from_secs(20), || {
        master = TcpStream::connect(("127.0.0.1", port)).ok();
        master.is_some()
    });
    let mut master = master.unwrap();
    master.set_nodelay(true).unwrap();
    master
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    // Fixed buffers: the master allocates nothing itself.
    let mut transact = |tid: u16| {
        let [hi, lo] = tid.to_be_bytes();
        master
            .write_all(&[hi, lo, 0, 0, 0, 6, 1, 3, 0, 0, 0, 1])
            .unwrap();
        let mut reply = [0u8; 11];
        master.read_exact(&mut reply).unwrap();
        assert_eq!(&reply[..2], &[hi, lo], "the master's own transaction id");
        assert_eq!(&reply[6..9], &[1, 3, 2], "unit 1, FC 03, two bytes");
    };
    for tid in 0..WARM {
        transact(tid);
    }
    let before = ALLOCATIONS.load(Ordering::Relaxed);
    for tid in WARM..WARM + COUNTED {
        transact(tid);
    }
    let counted = ALLOCATIONS.load(Ordering::Relaxed) - before;
    drop(master);
    shutdown.cancel();
    gateway.join().unwrap().unwrap();
    let _ = sim.kill();
    let _ = sim.wait();
    counted
}

fn check(framing: &str) {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let n = allocations_a_run(framing);
    eprintln!("{framing}: {n} allocations in {COUNTED} transactions");
    assert_eq!(
        n, 0,
        "{framing}: {n} allocations in {COUNTED} transactions of one master"
    );
}

#[test]
fn a_transaction_on_an_mbap_line_allocates_nothing() {
    check("mbap");
}

#[test]
fn a_transaction_on_an_rtu_line_allocates_nothing() {
    check("rtu");
}
