//! Who may talk to the device, and what they may do (docs/security.md): each
//! listener's allow list of source addresses ([`allow`]), and the listener's and each
//! role's policy for requests that may act on the device ([`rules`]). Plain data and
//! pure; the connection (src/masters/tcp/mod.rs) applies them, TLS (src/tls/) tells the role.

pub(crate) mod allow;
pub(crate) mod rules;

pub(crate) use allow::source_of;
pub(crate) use allow::{AllowList, Net};
pub(crate) use rules::decide;
pub use rules::{Policy, UnitSet, Why, WriteRule};
