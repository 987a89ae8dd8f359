//! End to end against peers: the mbgate binary as users run it, on socat ptys and
//! 127.0.0.1, against pymodbus, mbpoll, openssl, curl, tshark, Chromium, Prometheus and
//! scripted raw peers. One module a promise; tests/README.md says what each proves.
//! One area: `cargo test --test e2e dial::`.

#[path = "../common/mod.rs"]
mod common;

mod alerts;
mod answers;
mod bridge;
mod capture;
mod cli;
mod client;
mod dial;
mod dial_hostile;
mod faults;
mod hostile;
mod lines;
mod master_line;
mod mbap_holes;
mod metrics;
mod mixed_lines;
mod order;
mod pressure;
mod priority;
mod reliability;
mod reload;
mod replay;
mod replug;
mod rs485;
mod rtu;
mod rtu_binding;
mod rtu_timing;
mod scan;
mod security;
mod serial_port;
mod sim;
mod status_page;
mod third_party;
mod udp_hostile;
mod units;
mod virtual_line;
mod web;
mod wrong_replies;
