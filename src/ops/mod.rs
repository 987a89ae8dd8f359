//! Operations: the numbers (metrics, stats), capture, logging and systemd's notify
//! (the control socket and reload, which steer the whole gateway, are its own:
//! `crate::gateway`).

pub mod capture;
pub mod logging;
pub mod metrics;
pub(crate) mod notify;
pub mod stats;
