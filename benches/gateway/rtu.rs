//! `rtu` and `rtu-backoff`: RTU throughput at 9600 baud and the gateway's CPU
//! meanwhile; a backed-off dead unit polled in a tight loop beside a healthy one.

use super::common::{cpu_ns, read_frame, read_req, Cfg, Gateway};
use super::report::{command, pct, Report};
use super::shared::{
    clock_ticks_per_second, connect, cpu_ticks, rtu_reply_len, tcp_throughput, Line,
};
use std::fmt::Write as _;
use std::io::Write as _;
use std::sync::Arc;
use std::thread;
use std::time::{Duration, Instant};

/// RTU bytes of an FC 03 read: address, function, address, quantity, CRC.
const RTU_REQ: usize = 8;

/// The simulator as an RTU device paced at `baud`, answering once probed, and the
/// gateway in front of it at the same speed without flow control.
fn rtu_line(baud: u32) -> (Line, Gateway) {
    let probe = mbgate::frame::rtu::encode(1, &[0x03, 0, 0, 0, 1]);
    let speed = baud.to_string();
    let line = Line::start_probed(
        &["--framing", "rtu", "--baud", &speed],
        &probe,
        rtu_reply_len(1),
    );
    // Paced as a wire at `baud`: the gateway is told so, and keeps a wire's gap.
    let cfg = Cfg::new(&line.socat.gw)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"")
        .serial("port_kind = \"wire\"")
        .serial(&format!("baud_rate = {baud}"));
    let gw = line.gateway_with(cfg, &[], &[]);
    (line, gw)
}

/// One master polls FC 03 through `mbgate run --framing rtu` at 9600 baud against the
/// simulator (`--framing rtu --baud 9600`): transactions per second against the wire
/// limit, and the gateway's CPU time meanwhile (utime + stime from /proc/PID/stat, and
/// schedstat), which a busy-waiting gateway would drive towards a whole core.
pub(super) fn rtu(r: &mut Report) {
    const BAUD: u32 = 9600;
    const CPU_BUDGET: Duration = Duration::from_secs(10);
    const BUDGET: Duration = Duration::from_secs(3);
    let (_line, gw) = rtu_line(BAUD);
    let pid = gw.proc.pid();
    let mut s = connect(&gw);
    let char_time = 10.0 / f64::from(BAUD);
    // 3.5 character times, the gap mbgate leaves before each request.
    let t35 = 3.5 * char_time;
    let mut t = String::from(
        "| registers | wire limit (no gaps) | limit with the 3.5-character gap before each request | through mbgate | mbgate / limit (no gaps) | mbgate / limit (with gap) |\n|---|---|---|---|---|---|\n",
    );
    let mut cpu_row = String::new();
    for qty in [1u16, 10] {
        let bytes = (RTU_REQ + rtu_reply_len(qty)) as f64;
        let limit = 1.0 / (bytes * char_time);
        let limit_gap = 1.0 / (bytes * char_time + t35);
        let budget = if qty == 1 { CPU_BUDGET } else { BUDGET };
        eprintln!("rtu: {BAUD} baud, FC 03 × {qty}, {budget:?}");
        let (ticks0, ns0) = (cpu_ticks(pid), cpu_ns(pid));
        let got = tcp_throughput(&mut s, 1, qty, budget);
        let (ticks1, ns1) = (cpu_ticks(pid), cpu_ns(pid));
        let _ = writeln!(
            t,
            "| {qty} | {limit:.1}/s | {limit_gap:.1}/s | {got:.1}/s | {} | **{}** |",
            pct(got / limit),
            pct(got / limit_gap)
        );
        r.row(
            "rtu",
            &format!("RTU throughput {BAUD} baud, one master polling FC 03 × {qty}"),
            format!(
                "{got:.1}/s = {} of the wire limit with the 3.5-character gap ({limit_gap:.1}/s), {} without ({limit:.1}/s)",
                pct(got / limit_gap),
                pct(got / limit)
            ),
            "(reported)",
            None,
        );
        if qty == 1 {
            let hz = clock_ticks_per_second();
            let busy = (ticks1 - ticks0) as f64 / hz as f64;
            let share = busy / budget.as_secs_f64();
            let exact = (ns1 - ns0) as f64 / 1e9 / budget.as_secs_f64();
            cpu_row = format!(
                "utime+stime {} ticks in {} s = {} of a core (schedstat {})",
                ticks1 - ticks0,
                budget.as_secs(),
                pct(share),
                pct(exact)
            );
            r.row(
                "rtu",
                &format!("mbgate CPU, one master polling as fast as it can, RTU {BAUD} baud"),
                format!("{} of a core (schedstat {})", pct(share), pct(exact)),
                "< 5 % of a core",
                Some(share < 0.05),
            );
        }
    }
    let _ = writeln!(t, "\nCPU while polling FC 03 × 1 for 10 s: {cpu_row}.");
    r.detail(
        "RTU (the simulator with --framing rtu --baud 9600 paces 10 bits a byte each way; the wire limit counts request and reply bytes at 10 bits a byte, and the second limit adds the 3.5 character times mbgate waits before each request)",
        &command("rtu"),
        &t,
    );
}

/// A master polls a dead unit (2) in a tight loop beside a master polling a healthy
/// one (1), RTU at 19 200 baud, every `[relay]` key at its default: once the dead unit
/// is backed off, how fast its 0x0B answers come against the line's pace, what they
/// cost the gateway (utime + stime and schedstat, the healthy master idle), and the
/// healthy unit's throughput beside it against alone (probes of the dead unit
/// included).
pub(super) fn rtu_backoff(r: &mut Report) {
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    const BAUD: u32 = 19_200;
    const ALONE: Duration = Duration::from_secs(5);
    const CPU_WINDOW: Duration = Duration::from_secs(5);
    const BESIDE: Duration = Duration::from_secs(10);
    let (_line, gw) = rtu_line(BAUD);
    let pid = gw.proc.pid();
    let mut healthy = connect(&gw);
    eprintln!("rtu-backoff: the healthy unit alone, {ALONE:?}");
    let alone = tcp_throughput(&mut healthy, 1, 1, ALONE);

    let answered = Arc::new(AtomicUsize::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let (answered2, stop2) = (answered.clone(), stop.clone());
    let mut s = connect(&gw);
    let dead = thread::spawn(move || {
        let mut tid = 0u16;
        let mut slow = 0usize;
        while !stop2.load(Ordering::Relaxed) && tid < u16::MAX {
            tid += 1;
            let t = Instant::now();
            s.write_all(&read_req(tid, 2, 0, 1)).expect("send");
            let reply = read_frame(&mut s);
            assert_eq!(reply[7..], [0x83, 0x0B], "not 0x0B: {reply:02X?}");
            if t.elapsed() > Duration::from_millis(200) {
                slow += 1;
            }
            answered2.fetch_add(1, Ordering::Relaxed);
        }
        slow
    });
    // Three timeouts of 1 s and their 100 ms guards back it off.
    eprintln!("rtu-backoff: backing the dead unit off");
    thread::sleep(Duration::from_millis(3500));
    eprintln!("rtu-backoff: the dead unit polled alone, {CPU_WINDOW:?}");
    let (n0, ticks0, ns0, t0) = (
        answered.load(Ordering::Relaxed),
        cpu_ticks(pid),
        cpu_ns(pid),
        Instant::now(),
    );
    thread::sleep(CPU_WINDOW);
    let (n1, ticks1, ns1, t1) = (
        answered.load(Ordering::Relaxed),
        cpu_ticks(pid),
        cpu_ns(pid),
        Instant::now(),
    );
    eprintln!("rtu-backoff: the healthy unit beside it, {BESIDE:?}");
    let beside = tcp_throughput(&mut healthy, 1, 1, BESIDE);
    stop.store(true, Ordering::Relaxed);
    let slow = dead.join().unwrap();

    let secs = (t1 - t0).as_secs_f64();
    let rate = (n1 - n0) as f64 / secs;
    // The line's shortest transaction: 8 bytes out, 5 back, each after 3.5 characters.
    let char_time = 10.0 / f64::from(BAUD);
    let line_rate = 1.0 / (13.0 * char_time + 2.0 * 0.00175);
    let share = (ticks1 - ticks0) as f64 / clock_ticks_per_second() as f64 / secs;
    let exact = (ns1 - ns0) as f64 / 1e9 / secs;
    r.row(
        "rtu-backoff",
        "backed-off unit polled in a tight loop, RTU 19 200 baud: 0x0B answers and mbgate CPU",
        format!(
            "{rate:.1}/s (the line's pace {line_rate:.1}/s); {} of a core (schedstat {})",
            pct(share),
            pct(exact)
        ),
        "≤ the line's pace; < 5 % of a core",
        Some(rate <= line_rate * 1.05 && share < 0.05),
    );
    r.row(
        "rtu-backoff",
        "healthy unit beside it: throughput against alone",
        format!(
            "{beside:.1}/s beside, {alone:.1}/s alone = {} (dead unit: {slow} answers slower than 200 ms, the 3 timeouts that backed it off and its probes)",
            pct(beside / alone)
        ),
        "≥ 90 %",
        Some(beside >= alone * 0.9),
    );
}
