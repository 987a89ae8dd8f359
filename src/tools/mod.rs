//! The tools beside the gateway: the simulator, the master client, the bus scan, the
//! virtual wire and the demo.

pub mod client;
pub mod demo;
pub mod scan;
pub mod sim;
pub mod wire;
