//! The masters' side: where requests come from (listeners, dials, UDP, TLS), who may
//! send them (access) and which line serves them (router).

pub mod access;
pub(crate) mod router;
pub(crate) mod tcp;
pub mod tls;
