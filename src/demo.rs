//! `mbgate demo` (design.md §3, issue 3): no hardware. A pty pair made in-process, the
//! simulated device on one end, the gateway on the other, and instructions on how to
//! connect. This is the README's "run it" command on a machine without a device.

use crate::config::{Config, FlowControl, Notifications};
use crate::gateway::{self, GatewayError};
use crate::sim::options::{DeviceArgs, Settings};
use crate::sim::serve::{self, ConsoleRequest, Port, SimError};
use crate::sim::Profile;
use std::net::SocketAddr;
use tokio::sync::mpsc;
use tokio_serial::{SerialPort, SerialStream};
use tokio_util::sync::CancellationToken;

#[derive(Debug, Clone, clap::Args)]
pub struct DemoArgs {
    /// Where Modbus/TCP masters connect.
    #[arg(long, default_value = "127.0.0.1:5020", value_name = "ADDR")]
    pub listen: SocketAddr,
    /// Log every frame the gateway relays, both directions, as hex.
    #[arg(long)]
    pub traffic: bool,
    #[command(flatten)]
    pub device: DeviceArgs,
}

#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    #[error("cannot create a pty pair: {0}")]
    Pty(#[from] tokio_serial::Error),
    #[error("the pty pair has no name")]
    Unnamed,
    #[error(transparent)]
    Gateway(#[from] GatewayError),
    #[error(transparent)]
    Sim(#[from] SimError),
}

impl DemoArgs {
    /// The gateway's configuration: defaults, the pty, the listen address; device
    /// notifications reach every master when the simulator sends them. The line is
    /// as fast as the simulator's `--baud`, or the fastest there is when it is
    /// unpaced (a pty passes bytes at once; the gateway takes a reply that begins
    /// before its request could have left the wire for an echo), and a pty has no USB
    /// latency to wait out.
    pub fn gateway_config(&self, pty: String) -> Config {
        let mut cfg = Config::default();
        cfg.serial.path = pty;
        cfg.serial.baud_rate = self.device.baud.unwrap_or(4_000_000);
        cfg.serial.silence_floor_ms = 0;
        cfg.serial.flow_control = FlowControl::None;
        cfg.tcp.listen = self.listen;
        cfg.log.traffic = self.traffic;
        if self.device.notify {
            cfg.relay.notifications = Notifications::Broadcast;
        }
        cfg
    }
}

/// How to talk to the demo, printed once the gateway listens.
fn instructions(settings: &Settings, pty: &str, at: SocketAddr) -> String {
    let device = match &settings.device.profile {
        Profile::CieM10(d) => {
            let unit = if d.unit == 1 {
                String::new()
            } else {
                format!(" --unit {}", d.unit)
            };
            format!(
                "a simulated CIE-M10 (unit {}) on {pty}\n\n\
                 read the 8 inputs (FC 03):     mbgate read --tcp {at}{unit} holding {}\n\
                 drive outputs 0 and 4 (FC 16): mbgate write --tcp {at}{unit} holding {} 0x11 --multiple\n\
                 read the outputs back:         mbgate read --tcp {at}{unit} holding {}\n",
                d.unit, d.input_address, d.output_address, d.output_address,
            )
        }
        Profile::Generic(g) => {
            let units: Vec<String> = g.units.keys().map(u8::to_string).collect();
            format!(
                "simulated devices (units {}) on {pty}\n\n\
                 read holding registers:  mbgate read --tcp {at} holding 0 10\n\
                 write a coil:            mbgate write --tcp {at} coils 0 on\n",
                units.join(","),
            )
        }
    };
    format!("mbgate demo: {device}\nAny Modbus/TCP master can connect to {at}. Ctrl-C stops.\n")
}

/// Runs the demo until `shutdown`.
pub async fn run(
    args: &DemoArgs,
    settings: Settings,
    commands: mpsc::Receiver<ConsoleRequest>,
    shutdown: CancellationToken,
) -> Result<(), DemoError> {
    let (device_end, gateway_end) = SerialStream::pair()?;
    let pty = gateway_end.name().ok_or(DemoError::Unnamed)?;
    let cfg = args.gateway_config(pty.clone());
    let listener = gateway::bind(&cfg).await?;
    let at = listener.local_addr().map_err(|source| GatewayError::Bind {
        addr: cfg.tcp.listen,
        source,
    })?;
    print!("{}", instructions(&settings, &pty, at));
    let sim = tokio::spawn(serve::run(
        settings,
        Port::Stream(device_end),
        commands,
        shutdown.clone(),
    ));
    let served = gateway::serve(listener, cfg, shutdown.clone()).await;
    shutdown.cancel();
    let simulated = sim.await.unwrap_or(Ok(()));
    // The gateway's end stays open until both are done, so the device end never
    // sees the pty hang up.
    drop(gateway_end);
    served?;
    simulated?;
    Ok(())
}
