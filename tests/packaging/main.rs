//! What ships beside the code and how its host meets it: the README and docs/ run as
//! printed (their examples on fixed ports and /tmp paths, one block at a time), the
//! systemd units, journald and the notify protocol, scripts/test's install step, and a
//! new user's first hour. tests/README.md says what each module proves.
//! One area: `cargo test --test packaging docs::`.

#[path = "../common/mod.rs"]
mod common;

mod docs;
mod first_hour;
mod install_step;
mod journald;
mod notify;
mod systemd;
