//! The exception codes of an exception reply (Modbus Application Protocol V1.1b3 §7),
//! beside the function codes they answer (`function.rs`).

use std::fmt;

/// The exception code of an exception reply (V1.1b3 §7). Any byte is representable; a
/// device may only answer with the known (`ExceptionCode::is_known`) ones.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ExceptionCode(u8);

impl ExceptionCode {
    pub(crate) const ILLEGAL_FUNCTION: Self = Self(0x01);
    pub(crate) const ILLEGAL_DATA_ADDRESS: Self = Self(0x02);
    pub(crate) const ILLEGAL_DATA_VALUE: Self = Self(0x03);
    pub(crate) const SERVER_DEVICE_FAILURE: Self = Self(0x04);
    pub(crate) const ACKNOWLEDGE: Self = Self(0x05);
    pub(crate) const SERVER_DEVICE_BUSY: Self = Self(0x06);
    pub(crate) const MEMORY_PARITY_ERROR: Self = Self(0x08);
    /// The gateway cannot route the request: no serial port, or shutting down.
    pub(crate) const GATEWAY_PATH_UNAVAILABLE: Self = Self(0x0A);
    /// The device did not answer in time.
    pub(crate) const GATEWAY_TARGET_FAILED: Self = Self(0x0B);

    /// The code of this wire byte, whatever it is.
    pub(crate) const fn new(byte: u8) -> Self {
        Self(byte)
    }

    /// The wire byte.
    pub(crate) const fn get(self) -> u8 {
        self.0
    }

    /// Is it one of the codes of V1.1b3 §7, the only ones a device may answer with?
    pub(crate) fn is_known(self) -> bool {
        self.name().is_some()
    }

    /// Its name in V1.1b3 §7.
    pub(crate) fn name(self) -> Option<&'static str> {
        Some(match self {
            Self::ILLEGAL_FUNCTION => "illegal function",
            Self::ILLEGAL_DATA_ADDRESS => "illegal data address",
            Self::ILLEGAL_DATA_VALUE => "illegal data value",
            Self::SERVER_DEVICE_FAILURE => "server device failure",
            Self::ACKNOWLEDGE => "acknowledge",
            Self::SERVER_DEVICE_BUSY => "server device busy",
            Self::MEMORY_PARITY_ERROR => "memory parity error",
            Self::GATEWAY_PATH_UNAVAILABLE => "gateway path unavailable",
            Self::GATEWAY_TARGET_FAILED => "gateway target device failed to respond",
            _ => return None,
        })
    }
}

impl From<u8> for ExceptionCode {
    fn from(byte: u8) -> Self {
        Self(byte)
    }
}

impl From<ExceptionCode> for u8 {
    fn from(code: ExceptionCode) -> u8 {
        code.0
    }
}

impl PartialEq<u8> for ExceptionCode {
    fn eq(&self, other: &u8) -> bool {
        self.0 == *other
    }
}

impl fmt::Debug for ExceptionCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ExceptionCode({:#04x})", self.0)
    }
}

impl fmt::Display for ExceptionCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:#04x}", self.0)
    }
}
