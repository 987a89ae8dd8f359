//! Operations: the numbers (metrics, stats), capture, logging and systemd's notify
//! (the control socket and reload, which steer the whole gateway, are its own:
//! `crate::gateway`).

pub mod capture;
pub(crate) mod logging;
pub(crate) mod metrics;
pub(crate) mod notify;
pub mod stats;
