//! The flags of `mbgate demo` and `mbgate demo --master`, and where both demos listen
//! unless told: read by both demos (`demo/mod.rs`, `demo/master.rs`), neither of which
//! imports the other.

use crate::tools::sim::options::{DeviceArgs, Settings};
use std::net::SocketAddr;

/// Where the demo listens unless told: the port pymodbus' examples use too, so on a
/// clash the demo takes a free one instead.
pub(crate) const DEFAULT_LISTEN: SocketAddr =
    SocketAddr::new(std::net::IpAddr::V4(std::net::Ipv4Addr::LOCALHOST), 5020);

/// `mbgate demo`'s flags.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct DemoArgs {
    /// Where Modbus/TCP masters connect [default: 127.0.0.1:5020, or a free port when
    /// another program holds 5020]
    #[arg(long, value_name = "ADDR")]
    pub(crate) listen: Option<SocketAddr>,
    /// Log every frame the gateway relays, both directions, as hex.
    #[arg(long)]
    pub(crate) traffic: bool,
    /// Pace the simulated device's output at this many bits a second (10 bits a byte),
    /// as a UART would.
    #[arg(long, value_name = "BAUD", help_heading = "line model")]
    pub(crate) baud: Option<u32>,
    /// Two lines behind the one address: a second pty pair with the same simulated
    /// device, its units reached as unit + 100 (routing by unit, with remapping)
    #[arg(long, value_name = "N", default_value_t = 1,
          value_parser = clap::value_parser!(u8).range(1..=2))]
    pub(crate) lines: u8,
    /// The simulated device, as `mbgate sim` takes it.
    #[command(flatten)]
    pub(crate) device: DeviceArgs,
    /// The device as master instead (src/tools/demo/master.rs).
    #[command(flatten)]
    pub(crate) master: MasterDemoArgs,
}

impl DemoArgs {
    /// The simulated device's settings, paced at `--baud` if given.
    pub(crate) fn settings(&self) -> Result<Settings, crate::tools::sim::options::BadFlags> {
        if self.baud == Some(0) {
            return Err("--baud must be positive".into());
        }
        let mut s = self.device.settings()?;
        s.baud = self.baud;
        Ok(s)
    }
}

/// `mbgate demo --master` and its flags.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct MasterDemoArgs {
    /// The device as master: a simulated CIE-M10 master, mbgate's master line and a
    /// simulated CIE-M10 slave on Modbus/TCP (at --listen).
    #[arg(long, help_heading = "the device as master")]
    pub(crate) master: bool,
    /// --master: the master's communication period, in ms.
    #[arg(
        long,
        default_value_t = 1000,
        value_name = "MS",
        requires = "master",
        help_heading = "the device as master"
    )]
    pub(crate) poll_ms: u64,
}
