//! mbgate: a Modbus/TCP gateway to serial devices (design.md).

pub mod config;
pub mod frame;
pub mod gateway;
pub mod logging;
pub mod notify;
pub mod relay;
pub mod serial;
pub mod stats;
pub mod tcp;
pub mod tids;
