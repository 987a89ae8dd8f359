//! mbgate: a Modbus/TCP gateway to serial devices (design.md).

pub mod config;
pub mod frame;
