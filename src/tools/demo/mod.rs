//! `mbgate demo` (docs/design.md §3): no hardware. A pty pair made in-process, the
//! simulated device on one end, the gateway on the other, and instructions on how to
//! connect. This is the README's first command, on a machine without a device.

mod args;
pub(crate) mod invocation;
pub(crate) mod master;

use crate::config::{Config, FlowControl, Notifications, Units, FASTEST_BAUD};
use crate::gateway::{self, GatewayError};
use crate::tools::sim::options::Settings;
use crate::tools::sim::serve::{self, ConsoleRequest, SimError, SimPort};
use crate::tools::sim::Profile;
pub(crate) use args::DemoArgs;
use args::DEFAULT_LISTEN;
use std::net::SocketAddr;
use tokio::sync::mpsc;
use tokio_serial::{SerialPort, SerialStream};
use tokio_util::sync::CancellationToken;

/// Why the demo stopped early.
#[derive(Debug, thiserror::Error)]
pub(crate) enum DemoError {
    /// The system gave no pseudo-terminal pair.
    #[error("cannot create a pty pair: {0}")]
    Pty(#[from] tokio_serial::Error),
    /// The pty pair's device end has no path to give the gateway.
    #[error("the pty pair has no name")]
    Unnamed,
    /// The gateway could not start.
    #[error(transparent)]
    Gateway(#[from] GatewayError),
    /// The simulated device failed.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// The device flags do not make a device; the message says why.
    #[error(transparent)]
    Settings(#[from] crate::tools::sim::options::BadFlags),
}

/// What the second line's units are called by the masters: unit + 100.
const SECOND_LINE_OFFSET: u8 = 100;

/// The simulated device's unit ids.
fn device_units(settings: &Settings) -> Vec<u8> {
    match &settings.device.profile {
        Profile::CieM10(d) => vec![d.unit],
        Profile::Generic(g) => g.units.keys().copied().collect(),
        Profile::Replay(r) => r.units(),
    }
}

/// The gateway of `cfg` with two lines: the first on its pty serving the device's
/// units as they are, the second on `second_pty` serving them as unit + 100.
fn two_lines(cfg: &mut Config, units: &[u8], second_pty: String) {
    let first = cfg.lines[0].clone();
    let line = |path: String, units: Units| {
        let mut line = first.clone();
        (line.serial.path, line.units) = (path, units);
        line
    };
    let as_they_are = Units {
        ids: units.iter().copied().collect(),
        ..Units::default()
    };
    let remap = units
        .iter()
        .filter_map(|&u| Some((u.checked_add(SECOND_LINE_OFFSET)?, u)))
        .collect();
    let plus_100 = Units {
        remap,
        ..Units::default()
    };
    cfg.lines = vec![
        line(first.serial.path.clone(), as_they_are),
        line(second_pty, plus_100),
    ];
}

impl DemoArgs {
    /// The gateway's configuration: defaults, the pty, the listen address; device
    /// notifications reach every master when the simulator sends them. The line is
    /// as fast as the simulator's `--baud`, or the fastest there is when it is
    /// unpaced; the gateway finds the port a pty (no wire, no latency to wait out).
    pub(crate) fn gateway_config(&self, pty: String) -> Config {
        let mut cfg = Config::default();
        cfg.lines[0].serial.path = pty;
        cfg.lines[0].serial.baud_rate = self.baud.unwrap_or(FASTEST_BAUD);
        cfg.lines[0].serial.flow_control = FlowControl::None;
        cfg.listeners[0].tcp.listen = self.listen.unwrap_or(DEFAULT_LISTEN);
        cfg.log.traffic = self.traffic;
        if self.device.notify {
            cfg.lines[0].relay.notifications = Notifications::Broadcast;
        }
        cfg
    }
}

/// How to talk to the demo, printed once the gateway listens; `me` is how to run this
/// very binary from the user's shell ([`crate::tools::demo::invocation::command`]).
fn instructions(settings: &Settings, pty: &str, at: SocketAddr, me: &str) -> String {
    let device = match &settings.device.profile {
        Profile::CieM10(d) => {
            let unit = if d.unit == 1 {
                String::new()
            } else {
                format!(" --unit {}", d.unit)
            };
            let (input, output, u) = (d.input_address, d.output_address, d.unit);
            format!(
                "a simulated CIE-M10 (unit {u}) on {pty}\n\n\
                 read the 8 inputs (FC 03):     {me} read --tcp {at}{unit} holding-registers {input}\n\
                 drive outputs 0 and 4 (FC 16): {me} write --tcp {at}{unit} holding-registers {output} 0x11 --multiple\n\
                 read the outputs back:         {me} read --tcp {at}{unit} holding-registers {output}\n\n\
                 What it answers, the CIE-M10 manual's register map (unit {u}):\n  \
                 FC 03 of 1 register at {input}: the 8 inputs; at {output}: the 8 outputs\n  \
                 FC 16 of 1 register at {output}: drive the outputs\n\
                 and an exception for anything else, as the device does: 01 for another\n\
                 function (FC 06, coils, input registers), 02 for another address or count.\n\
                 A device that answers the usual requests instead (FC 01-06, 0F, 10, 17;\n\
                 coils and registers 0-9 of units 1 and 2):\n  \
                 {me} demo --profile generic --units 1,2\n",
            )
        }
        Profile::Generic(g) => {
            let units: Vec<String> = g.units.keys().map(u8::to_string).collect();
            let first = g.units.keys().next().copied().unwrap_or(1);
            let unit = if first == 1 {
                String::new()
            } else {
                format!(" --unit {first}")
            };
            let devices = match units.as_slice() {
                [one] => format!("a simulated device (unit {one})"),
                many => format!("simulated devices (units {})", many.join(", ")),
            };
            format!(
                "{devices} on {pty}\n\n\
                 read holding registers:  {me} read --tcp {at}{unit} holding-registers 0 10\n\
                 write a coil:            {me} write --tcp {at}{unit} coils 0 on\n",
            )
        }
        Profile::Replay(_) => format!("a replayed capture on {pty}\n"),
    };
    format!("mbgate demo: {device}\nAny Modbus/TCP master can connect to {at}. Ctrl-C stops.\n")
}

/// How to reach the second line (`--lines 2`): its units as unit + 100.
fn second_line(settings: &Settings, pty: &str, at: SocketAddr, me: &str) -> String {
    let units = device_units(settings);
    let Some(&first) = units
        .iter()
        .find(|u| u.checked_add(SECOND_LINE_OFFSET).is_some())
    else {
        return String::new();
    };
    let unit = first + SECOND_LINE_OFFSET;
    let (table, at_reg, count) = match &settings.device.profile {
        Profile::CieM10(d) => ("holding-registers", d.input_address, 1),
        Profile::Generic(_) | Profile::Replay(_) => ("holding-registers", 0, 10),
    };
    format!(
        "\nand the same device on a second line, {pty}: the gateway routes unit {unit} there as unit {first}\n\n\
         read it through the second line: {me} read --tcp {at} --unit {unit} {table} {at_reg} {count}\n"
    )
}

/// The gateway's listeners bound, and the first one's address: the default port
/// held by another program, a free one instead (unless `--listen` was given).
async fn bind(
    cfg: &mut crate::config::Config,
    listen_given: bool,
) -> Result<(Vec<crate::masters::tcp::Socket>, SocketAddr), DemoError> {
    let listener = match gateway::bind(cfg).await {
        Err(GatewayError::Bind { error, .. })
            if !listen_given && error.kind() == std::io::ErrorKind::AddrInUse =>
        {
            cfg.listeners[0].tcp.listen = SocketAddr::new(DEFAULT_LISTEN.ip(), 0);
            let listener = gateway::bind(cfg).await?;
            println!(
                "mbgate demo: another program holds {DEFAULT_LISTEN}; using a free port instead"
            );
            listener
        }
        bound => bound?,
    };
    let at = listener[0]
        .local_addr()
        .map_err(|error| GatewayError::Bind {
            addr: cfg.listeners[0].tcp.listen,
            error,
        })?;
    Ok((listener, at))
}

/// Runs the demo until `shutdown`; the gateway's counters at the end. `banner_shown`
/// hears once the instructions are printed (the console waits for them).
pub(crate) async fn run(
    args: &DemoArgs,
    settings: Settings,
    commands: mpsc::Receiver<ConsoleRequest>,
    shutdown: CancellationToken,
    banner_shown: std::sync::mpsc::Sender<()>,
) -> Result<std::sync::Arc<crate::ops::stats::Stats>, DemoError> {
    let (device_end, gateway_end) = SerialStream::pair()?;
    let pty = gateway_end.name().ok_or(DemoError::Unnamed)?;
    let mut cfg = args.gateway_config(pty.clone());
    // `--lines 2`: a second pty pair and the same device on it.
    let mut second = None;
    if args.lines > 1 {
        let (device_end, gateway_end) = SerialStream::pair()?;
        let pty = gateway_end.name().ok_or(DemoError::Unnamed)?;
        two_lines(&mut cfg, &device_units(&settings), pty.clone());
        let settings = args.settings()?;
        second = Some((device_end, gateway_end, pty, settings));
    }
    let (listener, at) = bind(&mut cfg, args.listen.is_some()).await?;
    let me = crate::tools::demo::invocation::command();
    print!("{}", instructions(&settings, &pty, at, &me));
    if let Some((_, _, second_pty, _)) = &second {
        print!("{}", second_line(&settings, second_pty, at, &me));
    }
    let _ = banner_shown.send(());
    // The console talks to the first line's device; the second's hears nothing.
    let (_quiet, no_commands) = mpsc::channel(1);
    let second = second.map(|(device_end, gateway_end, _, settings)| {
        let sim = serve::run(
            settings,
            SimPort::Stream(device_end),
            no_commands,
            shutdown.clone(),
        );
        (tokio::spawn(sim), gateway_end)
    });
    let sim = tokio::spawn(serve::run(
        settings,
        SimPort::Stream(device_end),
        commands,
        shutdown.clone(),
    ));
    let served = gateway::serve(listener, cfg, shutdown.clone()).await;
    shutdown.cancel();
    let simulated = sim.await.unwrap_or(Ok(()));
    // The gateway's end stays open until both are done, so the device end never
    // sees the pty hang up.
    drop(gateway_end);
    if let Some((sim, gateway_end)) = second {
        sim.await.unwrap_or(Ok(()))?;
        drop(gateway_end);
    }
    let stats = served?;
    simulated?;
    Ok(stats)
}
