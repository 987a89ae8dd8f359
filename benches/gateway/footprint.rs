//! `footprint`: start-up time, CPU while idle with 10 masters connected, RSS with 100,
//! and the release binary's size.

use super::common::cpu_ns;
use super::report::{command, ms, spread, Report};
use super::shared::{
    clock_ticks_per_second, connect, cpu_ticks, peak_rss_row, proc_status, tcp_read, Line,
};
use std::fmt::Write as _;
use std::net::TcpStream;
use std::path::Path;
use std::sync::{Arc, Barrier};
use std::thread;
use std::time::Duration;

fn file_size(path: &Path) -> u64 {
    std::fs::metadata(path).map(|m| m.len()).unwrap_or(0)
}

pub(super) fn footprint(r: &mut Report) {
    eprintln!("footprint: start-up, idle CPU with 10 masters, RSS with 100");
    let line = Line::start(&[]);
    let mut t = String::from("| what | figure |\n|---|---|\n");

    // Time from spawn to the `listening on` line, five starts.
    let mut starts = Vec::new();
    for _ in 0..5 {
        let mut gw = line.gateway(&[], &[]);
        starts.push(gw.proc.ready_after());
        gw.terminate(Duration::from_secs(5));
    }
    let st = spread(&starts);
    let _ = writeln!(
        t,
        "| start to `listening on`, 5 starts | median {}, max {} |",
        ms(st.p50),
        ms(st.max)
    );
    r.row(
        "footprint",
        "start to listening (median of 5)",
        ms(st.p50),
        "(reported)",
        None,
    );

    let gw = line.gateway(&["queue_depth = 256"], &["max_connections = 128"]);
    let pid = gw.proc.pid();
    let rss_start = proc_status(pid, "VmRSS");
    let mut masters: Vec<TcpStream> = (0..10).map(|_| connect(&gw)).collect();
    for (i, m) in masters.iter_mut().enumerate() {
        tcp_read(m, i as u16, 1);
    }
    // Idle: 10 masters connected, nothing asked, for 10 s.
    let (ticks0, ns0, sw0) = (
        cpu_ticks(pid),
        cpu_ns(pid),
        proc_status(pid, "voluntary_ctxt_switches"),
    );
    thread::sleep(Duration::from_secs(10));
    let (ticks1, ns1, sw1) = (
        cpu_ticks(pid),
        cpu_ns(pid),
        proc_status(pid, "voluntary_ctxt_switches"),
    );
    let hz = clock_ticks_per_second();
    let idle_ms = (ticks1 - ticks0) as f64 * 1000.0 / hz as f64;
    let idle_exact = Duration::from_nanos(ns1 - ns0);
    let _ = writeln!(
        t,
        "| CPU while idle, 10 masters connected, 10 s | utime+stime {} ticks ({idle_ms:.0} ms at {hz} ticks/s); schedstat {}; {} voluntary context switches |",
        ticks1 - ticks0,
        ms(idle_exact),
        sw1 - sw0
    );
    r.row(
        "footprint",
        "CPU while idle, 10 masters connected, 10 s",
        format!(
            "{} (schedstat), {} ticks, {} wake-ups",
            ms(idle_exact),
            ticks1 - ticks0,
            sw1 - sw0
        ),
        "< 10 ms",
        Some(idle_exact < Duration::from_millis(10) && idle_ms < 10.0),
    );

    // 100 masters connected, each has had a reply.
    masters.extend((10..100).map(|_| connect(&gw)));
    let barrier = Arc::new(Barrier::new(masters.len()));
    let masters: Vec<TcpStream> = masters
        .into_iter()
        .enumerate()
        .map(|(i, mut m)| {
            let b = barrier.clone();
            thread::spawn(move || {
                b.wait();
                tcp_read(&mut m, i as u16, 10);
                m
            })
        })
        .collect::<Vec<_>>()
        .into_iter()
        .map(|h| h.join().unwrap())
        .collect();
    let (rss, hwm, threads) = (
        proc_status(pid, "VmRSS"),
        proc_status(pid, "VmHWM"),
        proc_status(pid, "Threads"),
    );
    let _ = writeln!(
        t,
        "| RSS: at start / with 100 masters connected / peak (VmHWM) | {rss_start} kB / {rss} kB / {hwm} kB ({threads} threads) |"
    );
    peak_rss_row(
        r,
        "footprint",
        "peak RSS with 100 connected masters (VmHWM)",
        hwm,
    );
    drop(masters);

    let bin = Path::new(env!("CARGO_BIN_EXE_mbgate"));
    let size = file_size(bin);
    let stripped = std::env::temp_dir().join(format!("mbgate-stripped-{}", std::process::id()));
    let stripped_size = std::process::Command::new("strip")
        .arg("-o")
        .arg(&stripped)
        .arg(bin)
        .status()
        .ok()
        .filter(|s| s.success())
        .map(|_| file_size(&stripped));
    let _ = std::fs::remove_file(&stripped);
    let stripped_text = stripped_size.map_or("strip not found".into(), |s| {
        format!("{:.2} MiB stripped", s as f64 / 1048576.0)
    });
    let _ = writeln!(
        t,
        "| release binary `target/release/mbgate` | {size} bytes ({:.2} MiB); {stripped_text} |",
        size as f64 / 1048576.0
    );
    r.row(
        "footprint",
        "release binary size",
        format!("{:.2} MiB ({stripped_text})", size as f64 / 1048576.0),
        "(reported)",
        None,
    );
    r.detail("Footprint (the mbgate process: /proc/PID/status, /proc/PID/stat, /proc/PID/task/*/schedstat)", &command("footprint"), &t);
}
