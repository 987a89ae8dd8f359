//! mbgate: a Modbus/TCP gateway to serial devices (docs/design.md).

// Unsafe only where a SAFETY comment says why it is sound, each block allowed on its
// own (src/line/port/serial/: the ioctls, tcdrain, the descriptor's reads and writes and
// the timerfd; src/ops/control/: the peer's credentials and our effective user and group;
// src/tools/wire/pty.rs: the pty pair and its descriptors' flags).
#![deny(unsafe_code)]

pub mod cli;
pub mod config;
pub mod frame;
pub mod gateway;
pub mod line;
pub mod masters;
pub mod ops;
pub mod tools;
