//! The masters' side: where requests come from (listeners, dials, UDP, TLS) and which
//! line serves them (router); who may send them is `crate::access`, the TLS of both
//! sides `crate::tls`.

pub(crate) mod router;
pub(crate) mod tcp;
