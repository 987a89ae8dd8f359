//! The library driven in this process: the relay over an in-memory pipe, the decoders'
//! properties, the configuration read and refused (and the binary's `check-config` on
//! it). No socat, no Python, no peers: it runs where nothing else is installed.
//! tests/README.md says what each module proves. One area: `cargo test --test inprocess
//! config::`.

mod config;
mod decoder_props;
mod master_config;
mod relay_inprocess;
mod watching;
