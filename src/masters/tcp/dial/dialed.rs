//! A dialed connection's own state: the heartbeat it sends, the echoes of it and of
//! the identity the server may send back (`dial/echo.rs`), the reply last written
//! that reads as a request (`tcp/reflect.rs`), and how long the server may leave a
//! reply unread.

use super::echo;
use crate::masters::tcp::reflect::Loops;
use std::sync::Mutex;
use std::time::Duration;

/// What a dialed connection sends of its own, and the echoes it may get back.
pub(in crate::masters::tcp) struct Dialed {
    /// Sent after `every` without a reply written; empty: never.
    pub(in crate::masters::tcp) heartbeat: Vec<u8>,
    pub(in crate::masters::tcp) every: Duration,
    pub(in crate::masters::tcp) echoes: Mutex<echo::Echoes>,
    /// The last reply written that reads as a request (a write's): its echo is no
    /// request (`tcp/reflect.rs`).
    pub(in crate::masters::tcp) replied: Mutex<Loops>,
    /// How long the server may leave a reply unread before the connection is closed
    /// (and dialed again): never for ever, since mbgate has no other way to it.
    pub(in crate::masters::tcp) stall: Duration,
}
