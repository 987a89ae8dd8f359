//! The line: the loop that owns a device's line (relay), the master line (bridge), the
//! ports it is attached to, and a master's way back (outbox).

pub(crate) mod bridge;
pub mod outbox;
pub mod port;
pub mod relay;
pub(crate) mod woken;
