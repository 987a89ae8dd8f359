//! mbgate: a Modbus/TCP gateway to serial devices (docs/design.md).

// Unsafe only where a SAFETY comment says why it is sound, each block allowed on its
// own (src/port/serial/: the ioctls, tcdrain, the descriptor's reads and writes and
// the timerfd; src/control/: the peer's credentials and our effective user and group;
// src/wire/pty.rs: the pty pair and its descriptors' flags).
#![deny(unsafe_code)]

pub mod access;
pub mod bridge;
pub mod capture;
pub mod cli;
pub mod cli_overrides;
pub mod client;
pub mod config;
pub mod control;
pub mod demo;
pub mod frame;
pub mod gateway;
pub(crate) mod invocation;
pub mod logging;
pub mod manual;
pub mod metrics;
pub(crate) mod notify;
pub mod outbox;
pub mod port;
pub mod relay;
pub mod reload;
pub(crate) mod router;
pub mod runtime;
pub mod scan;
pub mod sim;
pub mod stats;
pub(crate) mod tcp;
pub(crate) mod tids;
pub mod tls;
pub mod wire;
pub(crate) mod woken;
