//! The tokio runtime every command runs on: one thread. The serial line is the
//! bottleneck, and a single-threaded runtime has the smallest footprint and no
//! cross-thread wake-ups on the reply path (docs/architecture.md).

use tokio::runtime::Runtime;

/// A single-threaded runtime with its I/O and timers on.
pub fn new() -> std::io::Result<Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
}
