//! The Modbus role extension reader (src/tls/role.rs) on hostile bytes: any input gives
//! an identity or an error, never a panic, and a role it returns is one mbgate will
//! compare and log (not empty, not too long, no control characters).
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbgate::tls::role::{identity, MAX_ROLE};

fuzz_target!(|data: &[u8]| {
    if let Ok(id) = identity(data) {
        if let Some(role) = id.role {
            assert!(!role.is_empty() && role.len() <= MAX_ROLE);
            assert!(!role.chars().any(char::is_control));
        }
    }
});
