//! The gateway benchmarks: added latency, wire efficiency, fairness and
//! footprint, measured side by side in one run against the device simulator on socat
//! pty pairs, and printed as Markdown.
//!
//! `cargo bench --bench gateway [-- SCENARIO...]`, SCENARIO one of `latency`, `wire`,
//! `fairness`, `footprint`, `rtu`, `rtu-backoff`, `rtu-limit`, `coalesce`, `tcp-line`,
//! `rtu-listener`, `dial`, `metrics`, `tls`, `capture`, `scale`, `units` (all when none is named). `rtu-limit`
//! compares with mbusd given `MBUSD=/path/to/mbusd`; `MBGATE_BENCH_BASELINE=PATH` names
//! another mbgate build (e.g. the commit before a change) that `coalesce` measures
//! beside this one. `scripts/bench` runs this and
//! `benches/decoder.rs` and writes the tables into docs/performance.md. With
//! `MBGATE_BENCH_MD=FILE` the tables are also written to FILE.
//!
//! This file picks the scenarios and prints the report; each scenario is a file of
//! benches/gateway/ named after it (`rtu` and `rtu-backoff` share rtu.rs, the timer
//! floor `rtu-limit` reports is timer_floor.rs), the report in report.rs and what
//! they share (peers, round trips, load loops, /proc figures) in shared.rs.
//!
//! Everything listens on 127.0.0.1 port 0; every load loop is bounded in count and
//! time. The masters run in this process (blocking sockets, one thread each); the
//! gateway (`mbgate run`) and the simulator (`mbgate sim`) are the release binaries.

#[path = "../tests/common/mod.rs"]
mod common;
#[path = "gateway/report.rs"]
mod report;
#[path = "gateway/shared.rs"]
mod shared;

// The scenarios, a file each (rtu.rs holds `rtu` and `rtu-backoff`).
#[path = "gateway/capture.rs"]
mod capture;
#[path = "gateway/coalesce.rs"]
mod coalesce;
#[path = "gateway/dial.rs"]
mod dial;
#[path = "gateway/fairness.rs"]
mod fairness;
#[path = "gateway/footprint.rs"]
mod footprint;
#[path = "gateway/latency.rs"]
mod latency;
#[path = "gateway/metrics.rs"]
mod metrics;
#[path = "gateway/rtu.rs"]
mod rtu;
#[path = "gateway/rtu_limit.rs"]
mod rtu_limit;
#[path = "gateway/rtu_listener.rs"]
mod rtu_listener;
#[path = "gateway/scale.rs"]
mod scale;
#[path = "gateway/tcp_line.rs"]
mod tcp_line;
#[path = "gateway/timer_floor.rs"]
mod timer_floor;
#[path = "gateway/tls.rs"]
mod tls;
#[path = "gateway/units.rs"]
mod units;
#[path = "gateway/wire.rs"]
mod wire;

use report::{loadavg, Report};

/// A benchmark scenario: it measures, and adds its rows and tables to the report.
type Scenario = fn(&mut Report);

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    // Each scenario by the name that picks it, in the order they run.
    let all: [(&str, Scenario); 16] = [
        ("latency", latency::latency),
        ("wire", wire::wire),
        ("fairness", fairness::fairness),
        ("footprint", footprint::footprint),
        ("rtu", rtu::rtu),
        ("rtu-backoff", rtu::rtu_backoff),
        ("rtu-limit", rtu_limit::rtu_limit),
        ("coalesce", coalesce::coalesce),
        ("tcp-line", tcp_line::tcp_line),
        ("rtu-listener", rtu_listener::rtu_listener),
        ("dial", dial::dial),
        ("metrics", metrics::metrics_cost),
        ("tls", tls::tls),
        ("capture", capture::capture_cost),
        ("scale", scale::scale),
        ("units", units::units_cost),
    ];
    let names: Vec<&str> = all.iter().map(|(name, _)| *name).collect();
    if let Some(bad) = args.iter().find(|a| !names.contains(&a.as_str())) {
        eprintln!("unknown scenario {bad:?}; scenarios: {}", names.join(", "));
        std::process::exit(2);
    }
    let wanted = |s: &str| args.is_empty() || args.iter().any(|a| a == s);
    let mut r = Report::default();
    let load_before = loadavg();
    for (name, scenario) in all {
        if wanted(name) {
            scenario(&mut r);
        }
    }
    let md = r.render(&load_before, &loadavg());
    println!("{md}");
    if let Some(path) = std::env::var_os("MBGATE_BENCH_MD") {
        std::fs::write(&path, &md).expect("write MBGATE_BENCH_MD");
    }
}
