//! The device simulator (docs/design.md §3 `mbgate sim`, docs/protocol.md §3 and §4): a
//! simulated device on a serial port or pty, speaking the gateway's framing, so nobody
//! needs a CIE-M10 on their desk.
//!
//! - `cie_m10` and [`generic`] are the device profiles (pure: PDU in, PDU out);
//! - `line` is the line model: seeded loss and noise, and a UART's pace;
//! - `console` parses the console's commands, `packets` keeps the packet log;
//! - [`serve`] is the task that owns the port, [`terminal`] the console's thread;
//! - [`replay`] is a device played back from a capture;
//! - [`pty`] is the pty it makes itself (`--pty`);
//! - [`options`] is the command line.

pub(crate) mod cie_m10;
pub(crate) mod console;
pub mod generic;
pub mod line;
pub(crate) mod master;
pub(crate) mod options;
pub(crate) mod packets;
pub(crate) mod pty;
pub(crate) mod replay;
pub(crate) mod role;
pub(crate) mod serve;
pub(crate) mod tcp;
pub(crate) mod terminal;

use crate::frame::function::{ExceptionCode, FunctionCode};
use console::{ConsoleCommand, Table};
use packets::PacketLog;

/// What a device does with one request: a reply PDU (or silence, for a unit id that is
/// not there), and an unsolicited notification PDU that the request caused.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Answer {
    pub(crate) reply: Option<Vec<u8>>,
    pub(crate) notification: Option<Vec<u8>>,
    /// How long this reply takes, beyond `--delay-ms` (a replayed device's own).
    pub(crate) delay: Option<std::time::Duration>,
}

impl Answer {
    pub(crate) fn silent() -> Self {
        Self::default()
    }

    pub(crate) fn reply(pdu: Vec<u8>) -> Self {
        Self {
            reply: Some(pdu),
            ..Self::default()
        }
    }
}

/// An exception response PDU (docs/protocol.md §1).
pub(crate) fn exception_pdu(function: FunctionCode, code: ExceptionCode) -> Vec<u8> {
    vec![function.exception().get(), code.get()]
}

/// Which device the simulator is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Profile {
    /// One Sollae CIE-M10/H10: eight inputs, eight outputs (docs/protocol.md §3).
    CieM10(cie_m10::CieM10),
    /// Any number of plain Modbus devices, each with its own tables.
    Generic(generic::Generic),
    /// Devices played back from a capture (`--replay`).
    Replay(Box<replay::Replay>),
}

/// The simulated device: its profile's state, the packet log, and what it needs to
/// create devices from the console.
#[derive(Debug)]
pub struct Device {
    /// What the device is, and its state (ports, tables).
    pub profile: Profile,
    pub(crate) log: PacketLog,
    /// Supplies the random discrete inputs of new generic devices (seeded).
    rng: fastrand::Rng,
    /// Sizes of a device added without them.
    pub(crate) default_bits: usize,
    pub(crate) default_registers: usize,
    /// What generic devices' holding registers start at, when not zero (`--fill`).
    fill: Option<fn(usize) -> u16>,
    /// Generic devices send an unsolicited frame on each scheduled change (`--notify`).
    generic_notify: bool,
    /// The generic profile's scheduled changes so far.
    ticks: u16,
}

/// What a console command produced.
#[derive(Debug, Default)]
pub(crate) struct ConsoleOutcome {
    /// Text for the console.
    pub(crate) text: String,
    /// A notification PDU to send (the inputs changed).
    pub(crate) notification: Option<Vec<u8>>,
    /// The console asked to stop; only the unit tests read it (the terminal stops
    /// on `ConsoleCommand::Quit` itself, src/tools/sim/terminal.rs).
    #[allow(dead_code)]
    pub(crate) quit: bool,
}

impl ConsoleOutcome {
    fn text(text: impl Into<String>) -> Self {
        Self {
            text: text.into(),
            ..Self::default()
        }
    }
}

/// The creation date and time of a device made now (UTC).
pub(crate) fn now_civil() -> [u16; 6] {
    generic::civil_time(std::time::SystemTime::now())
}

impl Device {
    pub(crate) fn new(profile: Profile, seed: u64) -> Self {
        Self {
            profile,
            log: PacketLog::default(),
            rng: fastrand::Rng::with_seed(seed),
            default_bits: generic::MIN_SIZE,
            default_registers: generic::MIN_SIZE,
            fill: None,
            generic_notify: false,
            ticks: 0,
        }
    }

    /// Holding registers start at their own address, in every generic device now and
    /// added later, so a reader can tell every value.
    pub(crate) fn fill_holding_with_addresses(&mut self) {
        self.fill_holding(|a| a as u16);
    }

    /// Holding register N holds `fill(N)`, in every generic device now and added later.
    pub(crate) fn fill_holding(&mut self, fill: fn(usize) -> u16) {
        self.fill = Some(fill);
        if let Profile::Generic(g) = &mut self.profile {
            for bank in g.units.values_mut() {
                bank.fill_holding(fill);
            }
        }
    }

    /// Generic devices notify each scheduled change: an unsolicited FC 03 response
    /// from the first unit, transaction id 0, carrying the count of changes.
    pub(crate) fn notify_generic(&mut self) {
        self.generic_notify = true;
    }

    /// A generic profile with a device on each of `units`, the reference simulator's way (docs/protocol.md §4).
    pub fn generic(units: &[u8], bits: usize, registers: usize, seed: u64) -> Self {
        let mut d = Self::new(Profile::Generic(generic::Generic::default()), seed);
        d.default_bits = bits;
        d.default_registers = registers;
        for &unit in units {
            d.add(unit, bits, registers);
        }
        d
    }

    fn add(&mut self, unit: u8, bits: usize, registers: usize) {
        let mut bank = generic::Bank::new(bits, registers, now_civil(), &mut self.rng);
        if let Some(fill) = self.fill {
            bank.fill_holding(fill);
        }
        if let Profile::Generic(g) = &mut self.profile {
            g.units.insert(unit, bank);
        }
    }

    /// Answers one request PDU for `unit`.
    pub(crate) fn answer(&mut self, unit: u8, pdu: &[u8]) -> Answer {
        match &mut self.profile {
            Profile::CieM10(d) => d.answer(unit, pdu),
            Profile::Generic(g) => g.answer(unit, pdu),
            Profile::Replay(r) => r.answer(unit, pdu),
        }
    }

    /// A broadcast request (unit 0 on an RTU/ASCII bus): every device acts on it, none
    /// answers.
    pub(crate) fn broadcast(&mut self, pdu: &[u8]) {
        match &mut self.profile {
            Profile::CieM10(d) => {
                let unit = d.unit;
                d.answer(unit, pdu);
            }
            Profile::Generic(g) => {
                let units: Vec<u8> = g.units.keys().copied().collect();
                for unit in units {
                    g.answer(unit, pdu);
                }
            }
            Profile::Replay(r) => r.broadcast(pdu),
        }
    }

    /// The unit id notifications come from, if the profile sends any.
    pub(crate) fn notifying_unit(&self) -> Option<u8> {
        match &self.profile {
            Profile::CieM10(d) => Some(d.unit),
            Profile::Generic(g) if self.generic_notify => g.units.keys().next().copied(),
            Profile::Generic(_) | Profile::Replay(_) => None,
        }
    }

    /// The scheduled input change (`--toggle-ms`): the CIE-M10's inputs count up by one,
    /// so every port changes in turn; the generic profile counts. Returns the
    /// notification, if any.
    pub(crate) fn toggle(&mut self) -> Option<Vec<u8>> {
        match &mut self.profile {
            Profile::CieM10(d) => {
                let next = d.inputs.wrapping_add(1);
                d.set_inputs(next);
                d.notification()
            }
            Profile::Generic(_) => {
                self.ticks = self.ticks.wrapping_add(1);
                let [hi, lo] = self.ticks.to_be_bytes();
                self.generic_notify.then(|| vec![3, 2, hi, lo])
            }
            Profile::Replay(_) => None,
        }
    }

    /// Carries out a console command.
    pub(crate) fn execute(&mut self, cmd: ConsoleCommand) -> ConsoleOutcome {
        match cmd {
            ConsoleCommand::Help => ConsoleOutcome::text(console::HELP),
            ConsoleCommand::Slave(_) => {
                ConsoleOutcome::text("`slave` commands are for the slave of mbgate demo --master")
            }
            ConsoleCommand::List => ConsoleOutcome::text(self.list()),
            ConsoleCommand::Log(n) => {
                ConsoleOutcome::text(self.log.render(n).trim_end().to_string())
            }
            ConsoleCommand::ClearLog => {
                let n = self.log.len();
                self.log.clear();
                ConsoleOutcome::text(format!("cleared {n} packets"))
            }
            ConsoleCommand::ClearScreen => ConsoleOutcome::text("\x1b[2J\x1b[H"),
            ConsoleCommand::Quit => ConsoleOutcome {
                quit: true,
                ..ConsoleOutcome::text("bye")
            },
            ConsoleCommand::Add {
                unit,
                bits,
                registers,
            } => self.console_add(unit, bits, registers),
            ConsoleCommand::Remove { unit } => match &mut self.profile {
                Profile::Generic(g) => match g.units.remove(&unit) {
                    Some(_) => ConsoleOutcome::text(format!("removed unit {unit}")),
                    None => ConsoleOutcome::text(format!("no unit {unit}")),
                },
                Profile::CieM10(_) => ConsoleOutcome::text("the cie-m10 profile is one device"),
                Profile::Replay(_) => ConsoleOutcome::text("a replay has the units it recorded"),
            },
            ConsoleCommand::Input { port, on } => self.cie_inputs(|inputs| {
                if on {
                    inputs | 1 << port
                } else {
                    inputs & !(1 << port)
                }
            }),
            ConsoleCommand::Inputs(v) => self.cie_inputs(|_| v),
            ConsoleCommand::Set {
                unit,
                table,
                address,
                value,
            } => self.set(unit, table, address, value),
        }
    }

    fn console_add(
        &mut self,
        unit: u8,
        bits: Option<usize>,
        registers: Option<usize>,
    ) -> ConsoleOutcome {
        let Profile::Generic(g) = &self.profile else {
            return ConsoleOutcome::text(
                "the cie-m10 profile is one device; use --profile generic",
            );
        };
        let bits = bits.unwrap_or(self.default_bits);
        let registers = registers.unwrap_or(self.default_registers);
        let sizes = generic::MIN_SIZE..=generic::MAX_SIZE;
        if !(1..=247).contains(&unit) {
            return ConsoleOutcome::text(format!("unit must be 1..247, not {unit}"));
        }
        if !sizes.contains(&bits) || !sizes.contains(&registers) {
            return ConsoleOutcome::text(format!(
                "coils and registers must be {}..{}",
                generic::MIN_SIZE,
                generic::MAX_SIZE
            ));
        }
        if g.units.contains_key(&unit) {
            return ConsoleOutcome::text(format!("unit {unit} exists; remove it first"));
        }
        self.add(unit, bits, registers);
        ConsoleOutcome::text(format!(
            "added unit {unit}: {bits} coils, {registers} registers"
        ))
    }

    fn cie_inputs(&mut self, f: impl FnOnce(u8) -> u8) -> ConsoleOutcome {
        let Profile::CieM10(d) = &mut self.profile else {
            return ConsoleOutcome::text(
                "inputs are the cie-m10 profile's; use `set` for generic devices",
            );
        };
        let changed = d.set_inputs(f(d.inputs));
        ConsoleOutcome {
            text: format!("inputs {:08b}", d.inputs),
            notification: changed.then(|| d.notification()).flatten(),
            quit: false,
        }
    }

    fn set(&mut self, unit: u8, table: Table, address: u16, value: u16) -> ConsoleOutcome {
        let Profile::Generic(g) = &mut self.profile else {
            return ConsoleOutcome::text("`set` is for generic devices; use `input` or `inputs`");
        };
        let Some(bank) = g.units.get_mut(&unit) else {
            return ConsoleOutcome::text(format!("no unit {unit}"));
        };
        let a = usize::from(address);
        let ok = match table {
            Table::Coils => bank.coils.get_mut(a).map(|s| *s = value != 0),
            Table::Discrete => bank.discrete.get_mut(a).map(|s| *s = value != 0),
            Table::Holding => bank.holding.get_mut(a).map(|s| *s = value),
            Table::Input => bank.input.get_mut(a).map(|s| *s = value),
        };
        match ok {
            Some(()) => ConsoleOutcome::text(format!("unit {unit} {table} {address} = {value}")),
            None => ConsoleOutcome::text(format!("unit {unit} has no {table} {address}")),
        }
    }

    fn list(&self) -> String {
        match &self.profile {
            Profile::CieM10(d) => {
                format!(
                "cie-m10 unit {}: inputs {:08b} at register {}, outputs {:08b} at register {}{}{}",
                d.unit,
                d.inputs,
                d.input_address,
                d.outputs,
                d.output_address,
                if d.loopback { ", inputs wired to outputs" } else { "" },
                if d.notify { ", change notification on" } else { "" },
            )
            }
            Profile::Generic(g) if g.units.is_empty() => "no devices".into(),
            Profile::Generic(g) => g
                .units
                .iter()
                .map(|(unit, bank)| format!("unit {unit}: {bank}"))
                .collect::<Vec<_>>()
                .join("\n"),
            Profile::Replay(r) => r.summary.clone(),
        }
    }
}

#[cfg(test)]
mod tests;
