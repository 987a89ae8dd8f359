//! `mbgate demo --master` (docs/device-as-master.md): no hardware, the other way
//! round. A simulated CIE-M10 master on one end of a pty pair, mbgate's master line on
//! the other, and a simulated CIE-M10 slave on Modbus/TCP: the master reads the slave's
//! inputs and drives its outputs every period, so an input set on one side shows on
//! the other. The console talks to the master; `slave COMMAND` to the slave.

use super::args::{DemoArgs, DEFAULT_LISTEN};
use crate::config::master::{MasterLine, Peer, Route};
use crate::config::{Config, FlowControl};
use crate::tools::sim::cie_m10::CieM10;
use crate::tools::sim::console::ConsoleCommand;
use crate::tools::sim::options::Settings;
use crate::tools::sim::role::Polling;
use crate::tools::sim::serve::{ConsoleRequest, SimPort};
use crate::tools::sim::{Device, Profile};
use std::net::SocketAddr;
use std::time::Duration;
use tokio::sync::mpsc;
use tokio_serial::{SerialPort, SerialStream};
use tokio_util::sync::CancellationToken;

/// Why the master demo stopped early.
#[derive(Debug, thiserror::Error)]
pub(crate) enum MasterDemoError {
    /// The system gave no pseudo-terminal pair.
    #[error("cannot create a pty pair: {0}")]
    Pty(#[from] tokio_serial::Error),
    /// The pty pair's device end has no path to give the master line.
    #[error("the pty pair has no name")]
    Unnamed,
    /// The simulated slave's address (`--listen`) could not be bound.
    #[error("cannot listen on {0}: {1}")]
    Bind(SocketAddr, std::io::Error),
    /// The gateway of the master line could not start.
    #[error(transparent)]
    Gateway(#[from] crate::gateway::GatewayError),
    /// A simulated device failed.
    #[error(transparent)]
    Sim(#[from] crate::tools::sim::serve::SimError),
}

/// The master line's configuration: the pty, as fast as it goes, one default route to
/// the slave.
fn line_config(pty: String, slave: SocketAddr, traffic: bool) -> Config {
    let mut cfg = Config::default();
    cfg.lines[0].serial.path = pty;
    cfg.lines[0].serial.baud_rate = crate::config::FASTEST_BAUD;
    cfg.lines[0].serial.flow_control = FlowControl::None;
    cfg.log.traffic = traffic;
    cfg.lines[0].master = Some(MasterLine {
        routes: vec![Route {
            units: Vec::new(),
            peer: Peer::Connect(slave.to_string()),
            response_timeout_ms: 1000,
            max_in_flight: 1,
            allow: None,
        }],
    });
    cfg
}

/// What the demo prints once it runs; `me` runs this binary from the user's shell.
fn instructions(pty: &str, slave: SocketAddr, poll_ms: u64, me: &str) -> String {
    format!(
        "mbgate demo --master: a simulated CIE-M10 master on {pty}, mbgate's master line, \
         and a simulated CIE-M10 slave on {slave}\n\
         Every {poll_ms} ms the master reads the slave's inputs (FC 03, register 0) and \
         writes its own inputs to the slave's outputs (FC 16, register 8).\n\n\
         at the sim> prompt:\n\
         \x20 input 0 on          the master's input 0; the slave's outputs follow:\n\
         \x20                     {me} read --tcp {slave} holding-registers 8\n\
         \x20 slave input 3 on    the slave's input 3; the master's outputs follow (shown here)\n\
         \x20 list, slave list    both devices' ports\n\
         Ctrl-C stops.\n"
    )
}

/// Binds the slave's address: `--listen`, else 127.0.0.1:5020, else a free port.
async fn bind_slave(
    listen: Option<SocketAddr>,
) -> Result<tokio::net::TcpListener, MasterDemoError> {
    let addr = listen.unwrap_or(DEFAULT_LISTEN);
    match crate::tools::sim::tcp::bind(addr).await {
        Err(e) if listen.is_none() && e.kind() == std::io::ErrorKind::AddrInUse => {
            let free = SocketAddr::new(addr.ip(), 0);
            crate::tools::sim::tcp::bind(free)
                .await
                .map_err(|e| MasterDemoError::Bind(free, e))
        }
        r => r.map_err(|e| MasterDemoError::Bind(addr, e)),
    }
}

/// The console's commands split: `slave ...` to the slave, the rest to the master.
fn split_console(
    mut commands: mpsc::Receiver<ConsoleRequest>,
) -> (
    mpsc::Receiver<ConsoleRequest>,
    mpsc::Receiver<ConsoleRequest>,
) {
    let (to_master, master_commands) = mpsc::channel(4);
    let (to_slave, slave_commands) = mpsc::channel(4);
    tokio::spawn(async move {
        while let Some(req) = commands.recv().await {
            let ConsoleRequest { command, reply } = req;
            let (to, command) = match command {
                ConsoleCommand::Slave(inner) => (&to_slave, *inner),
                other => (&to_master, other),
            };
            if to.send(ConsoleRequest { command, reply }).await.is_err() {
                return;
            }
        }
    });
    (master_commands, slave_commands)
}

/// Runs the demo until `shutdown`. `settings` are the master's (the device flags of
/// `mbgate demo`); the slave is a CIE-M10 with the manual's defaults.
pub(crate) async fn run(
    args: &DemoArgs,
    settings: Settings,
    commands: mpsc::Receiver<ConsoleRequest>,
    shutdown: CancellationToken,
    banner_shown: std::sync::mpsc::Sender<()>,
) -> Result<(), MasterDemoError> {
    let (device_end, gateway_end) = SerialStream::pair()?;
    let pty = gateway_end.name().ok_or(MasterDemoError::Unnamed)?;
    let listener = bind_slave(args.listen).await?;
    let slave_at = listener
        .local_addr()
        .map_err(|e| MasterDemoError::Bind(args.listen.unwrap_or(DEFAULT_LISTEN), e))?;
    let cfg = line_config(pty.clone(), slave_at, args.traffic);
    let me = crate::tools::demo::invocation::command();
    print!("{}", instructions(&pty, slave_at, args.master.poll_ms, &me));
    let _ = banner_shown.send(());

    let (master_commands, slave_commands) = split_console(commands);
    let slave = Device::new(Profile::CieM10(CieM10::default()), settings.seed);
    // The master line, and the user's own reads of the slave (the banner's).
    let slave = tokio::spawn(crate::tools::sim::tcp::run(
        slave,
        listener,
        8,
        slave_commands,
        shutdown.clone(),
    ));
    let line = {
        let shutdown = shutdown.clone();
        tokio::spawn(async move { crate::gateway::run(cfg, shutdown).await })
    };
    let polling = Polling {
        period: Duration::from_millis(args.master.poll_ms.max(1)),
        timeout: Duration::from_millis(args.master.poll_ms.clamp(1, 1000)),
    };
    let master = crate::tools::sim::master::run(
        settings,
        polling,
        SimPort::Stream(device_end),
        master_commands,
        shutdown.clone(),
    )
    .await;
    shutdown.cancel();
    let line = line.await.unwrap_or_else(|_| Ok(Default::default()));
    let _ = slave.await;
    // The line's end stays open until both are done, so the master never sees a hang-up.
    drop(gateway_end);
    line?;
    master?;
    Ok(())
}
