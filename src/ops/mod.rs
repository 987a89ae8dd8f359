//! Operations: the numbers (metrics, stats), capture, the control socket, reload,
//! logging and systemd's notify.

pub mod capture;
pub mod control;
pub mod logging;
pub mod metrics;
pub(crate) mod notify;
pub mod reload;
pub mod stats;
