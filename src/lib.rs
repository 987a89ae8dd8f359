//! mbgate: a Modbus/TCP gateway to serial devices (docs/design.md).

// Unsafe only where a SAFETY comment says why it is sound, each block allowed on its
// own: src/line/port/fd.rs (a descriptor on the reactor, its reads and writes, once for
// every user), src/line/port/serial/ (the ioctls, tcdrain, the timerfd, the tty's
// termios), src/gateway/control/mod.rs (our effective user and group) and
// src/tools/wire/pty.rs (the pty pair); docs/architecture.md "Who does what" names
// every file.
//
// `pub` is what the binary, tests/, benches/, the fuzz targets and the doc examples
// name; the rest is `pub(crate)` (docs/architecture.md "House rules": `unreachable_pub`
// and tests/packaging/docs/surface.rs hold it). `masters` is used only inside.
//
// The wings are layers, each importing only the wings below it: cli > tools > gateway >
// masters > line > ops > tls > config > access > frame (docs/architecture.md "The
// wings"; tests/packaging/docs/map.rs holds it). rustfmt keeps the lines below in
// alphabetical order, so that order is not this one.
#![deny(unsafe_code)]

pub mod access;
pub mod cli;
pub mod config;
pub mod frame;
pub mod gateway;
pub mod line;
pub(crate) mod masters;
pub mod ops;
pub mod tls;
pub mod tools;
