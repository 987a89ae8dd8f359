//! Pure frame code: bytes in, frames out. No tokio, no I/O, so every piece here can be
//! unit-tested, property-tested and fuzzed on its own (docs/design.md §5).

pub mod ascii;
pub mod framer;
pub mod function;
pub mod hex;
pub mod lossy;
pub mod mbap;
pub mod pdu;
pub mod request;
pub(crate) mod resync;
pub mod rtu;
pub mod serial;

pub(crate) use function::{ExceptionCode, FunctionCode};
pub use mbap::{Adu, StrictError};
pub use resync::{Confirmed, Judge, ReplyJudge, RequestJudge, Resync};
