//! The tools beside the gateway: the simulator, the master client, the bus scan, the
//! virtual wire and the demo.

pub(crate) mod client;
pub(crate) mod demo;
pub(crate) mod scan;
pub mod sim;
pub mod wire;
