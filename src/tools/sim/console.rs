//! The simulator's console (docs/protocol.md §4: the reference simulator's slave menu, as commands): add,
//! remove and list devices, set inputs and values, show and clear the packet log,
//! clear the screen, quit. Parsing only; the simulator carries the commands out.

use std::fmt;

/// A console line that is not a command; the message says what is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub(crate) enum BadCommand {
    #[error("unknown table `{0}`: coils, discrete, holding or input")]
    Table(String),
    #[error("not a number: `{0}`")]
    NotANumber(String),
    #[error("{what} out of range: {given}")]
    OutOfRange { what: String, given: String },
    #[error("port out of range: {0} (0..7)")]
    Port(u8),
    #[error("expected on or off, not `{0}`")]
    OnOff(String),
    #[error("usage: {0}")]
    Usage(&'static str),
    #[error("unknown command `{0}`; `help` lists them")]
    Unknown(String),
}

/// A table of the generic profile's devices.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Table {
    Coils,
    Discrete,
    Holding,
    Input,
}

impl Table {
    fn parse(s: &str) -> Result<Self, BadCommand> {
        Ok(match s {
            "coil" | "coils" | "co" => Table::Coils,
            "discrete" | "di" => Table::Discrete,
            "holding" | "hr" => Table::Holding,
            "input" | "ir" => Table::Input,
            _ => return Err(BadCommand::Table(s.to_owned())),
        })
    }
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum ConsoleCommand {
    Help,
    /// List the devices and their state.
    List,
    /// Add a device (generic profile): unit, coils, registers.
    Add {
        unit: u8,
        bits: Option<usize>,
        registers: Option<usize>,
    },
    Remove {
        unit: u8,
    },
    /// Set one input port of the CIE-M10 on or off.
    Input {
        port: u8,
        on: bool,
    },
    /// Set all eight input ports of the CIE-M10.
    Inputs(u8),
    /// Set a value in a generic device's table.
    Set {
        unit: u8,
        table: Table,
        address: u16,
        value: u16,
    },
    /// Show the last `n` packets (all when `None`).
    Log(Option<usize>),
    ClearLog,
    ClearScreen,
    Quit,
    /// `slave COMMAND`: for the simulated slave of `mbgate demo --master`.
    Slave(Box<ConsoleCommand>),
}

pub(crate) const HELP: &str = "\
commands:
  list                          devices and their state
  add UNIT [COILS [REGISTERS]]  add a device (generic; at least 10 of each)
  remove UNIT                   remove a device (generic)
  input PORT on|off             set one input port 0..7 (cie-m10)
  inputs VALUE                  set all eight input ports, e.g. 0xFF or 0b1010 (cie-m10)
  set UNIT TABLE ADDR VALUE     set coils|discrete|holding|input ADDR (generic)
  log [N]                       the packet log (the last N packets)
  clear-log                     empty the packet log
  clear                         clear the screen
  quit | q                      stop the simulator
  slave COMMAND                 mbgate demo --master: a command for the slave, e.g.
                                `slave input 3 on`";

fn bounded<T: TryFrom<i64>>(s: &str, what: &str) -> Result<T, BadCommand> {
    let n = crate::config::number::parse(s).ok_or_else(|| BadCommand::NotANumber(s.to_owned()))?;
    T::try_from(n).map_err(|_| BadCommand::OutOfRange {
        what: what.to_owned(),
        given: s.to_owned(),
    })
}

fn on_off(s: &str) -> Result<bool, BadCommand> {
    match s {
        "on" | "1" | "true" => Ok(true),
        "off" | "0" | "false" => Ok(false),
        _ => Err(BadCommand::OnOff(s.to_owned())),
    }
}

impl ConsoleCommand {
    /// Long because it is the console's table of commands: one arm each, its usage and
    /// its arguments side by side (docs/simulator.md lists the same).
    ///
    /// One console line; `Ok(None)` for an empty line.
    pub(crate) fn parse(line: &str) -> Result<Option<ConsoleCommand>, BadCommand> {
        let words: Vec<&str> = line.split_whitespace().collect();
        let Some((&first, args)) = words.split_first() else {
            return Ok(None);
        };
        let want = |n: std::ops::RangeInclusive<usize>, usage: &'static str| {
            if n.contains(&args.len()) {
                Ok(())
            } else {
                Err(BadCommand::Usage(usage))
            }
        };
        let cmd = match first.to_ascii_lowercase().as_str() {
            "help" | "h" | "?" => ConsoleCommand::Help,
            "list" | "ls" | "l" => ConsoleCommand::List,
            "add" => {
                want(1..=3, "add UNIT [COILS [REGISTERS]]")?;
                ConsoleCommand::Add {
                    unit: bounded(args[0], "unit")?,
                    bits: args.get(1).map(|s| bounded(s, "coils")).transpose()?,
                    registers: args.get(2).map(|s| bounded(s, "registers")).transpose()?,
                }
            }
            "remove" | "rm" => {
                want(1..=1, "remove UNIT")?;
                ConsoleCommand::Remove {
                    unit: bounded(args[0], "unit")?,
                }
            }
            "input" => {
                want(2..=2, "input PORT on|off")?;
                let port: u8 = bounded(args[0], "port")?;
                if port > 7 {
                    return Err(BadCommand::Port(port));
                }
                ConsoleCommand::Input {
                    port,
                    on: on_off(args[1])?,
                }
            }
            "inputs" => {
                want(1..=1, "inputs VALUE")?;
                ConsoleCommand::Inputs(bounded(args[0], "inputs")?)
            }
            "set" => {
                want(4..=4, "set UNIT TABLE ADDR VALUE")?;
                let table = Table::parse(args[1])?;
                let value = match table {
                    Table::Coils | Table::Discrete => u16::from(on_off(args[3])?),
                    _ => bounded(args[3], "value")?,
                };
                ConsoleCommand::Set {
                    unit: bounded(args[0], "unit")?,
                    table,
                    address: bounded(args[2], "address")?,
                    value,
                }
            }
            "log" => {
                want(0..=1, "log [N]")?;
                ConsoleCommand::Log(args.first().map(|s| bounded(s, "count")).transpose()?)
            }
            "clear-log" | "clearlog" => ConsoleCommand::ClearLog,
            "clear" | "cls" => ConsoleCommand::ClearScreen,
            "quit" | "q" | "exit" => ConsoleCommand::Quit,
            "slave" => {
                let rest = line.trim_start()[first.len()..].trim();
                match ConsoleCommand::parse(rest)? {
                    Some(ConsoleCommand::Slave(_)) | None => {
                        return Err(BadCommand::Usage("slave COMMAND"))
                    }
                    Some(inner) => ConsoleCommand::Slave(Box::new(inner)),
                }
            }
            other => return Err(BadCommand::Unknown(other.to_owned())),
        };
        Ok(Some(cmd))
    }
}

impl fmt::Display for Table {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Table::Coils => "coils",
            Table::Discrete => "discrete",
            Table::Holding => "holding",
            Table::Input => "input",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_seed_menu_as_commands() {
        let p = |s| ConsoleCommand::parse(s).unwrap().unwrap();
        assert_eq!(
            p("add 2 10 10"),
            ConsoleCommand::Add {
                unit: 2,
                bits: Some(10),
                registers: Some(10)
            }
        );
        assert_eq!(
            p("add 3"),
            ConsoleCommand::Add {
                unit: 3,
                bits: None,
                registers: None
            }
        );
        assert_eq!(p("remove 2"), ConsoleCommand::Remove { unit: 2 });
        assert_eq!(p("list"), ConsoleCommand::List);
        assert_eq!(p("log"), ConsoleCommand::Log(None));
        assert_eq!(p("log 5"), ConsoleCommand::Log(Some(5)));
        assert_eq!(p("clear-log"), ConsoleCommand::ClearLog);
        assert_eq!(p("Clear"), ConsoleCommand::ClearScreen);
        assert_eq!(p("Q"), ConsoleCommand::Quit);
        assert_eq!(p("input 4 on"), ConsoleCommand::Input { port: 4, on: true });
        assert_eq!(p("inputs 0b00010001"), ConsoleCommand::Inputs(0x11));
        assert_eq!(p("inputs 0xFF"), ConsoleCommand::Inputs(0xFF));
        assert_eq!(
            p("set 1 holding 0x10 65535"),
            ConsoleCommand::Set {
                unit: 1,
                table: Table::Holding,
                address: 16,
                value: 65535
            }
        );
        assert_eq!(
            p("set 1 coils 3 on"),
            ConsoleCommand::Set {
                unit: 1,
                table: Table::Coils,
                address: 3,
                value: 1
            }
        );
        assert_eq!(ConsoleCommand::parse("   ").unwrap(), None);
    }

    #[test]
    fn errors_say_what_is_wrong() {
        let e = |s| ConsoleCommand::parse(s).unwrap_err().to_string();
        assert_eq!(e("add"), "usage: add UNIT [COILS [REGISTERS]]");
        assert_eq!(e("add 300"), "unit out of range: 300");
        assert_eq!(e("input 8 on"), "port out of range: 8 (0..7)");
        assert_eq!(e("input 1 maybe"), "expected on or off, not `maybe`");
        assert_eq!(e("inputs 0x100"), "inputs out of range: 0x100");
        assert_eq!(
            e("set 1 foo 0 1"),
            "unknown table `foo`: coils, discrete, holding or input"
        );
        assert_eq!(
            e("frobnicate"),
            "unknown command `frobnicate`; `help` lists them"
        );
        assert_eq!(e("log x"), "not a number: `x`");
    }

    #[test]
    fn slave_prefix_wraps_one_command() {
        let p = |s| ConsoleCommand::parse(s);
        assert_eq!(
            p("slave input 3 on"),
            Ok(Some(ConsoleCommand::Slave(Box::new(
                ConsoleCommand::Input { port: 3, on: true }
            ))))
        );
        let e = |s| p(s).unwrap_err().to_string();
        assert_eq!(e("slave"), "usage: slave COMMAND");
        assert_eq!(e("slave slave list"), "usage: slave COMMAND");
        assert_eq!(e("slave input 9 on"), "port out of range: 9 (0..7)");
    }
}
