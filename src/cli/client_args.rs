//! `mbgate read` and `mbgate write`'s flags: where requests go and what they ask, as
//! the request PDUs of docs/protocol.md §1, and the session's options.

use crate::cli::overrides::{choice, PortFlags, PORT_GROUP};
use crate::config::{Framing, SerialConfig};
use crate::frame::request::Request;
use crate::tools::client::{ClientTransport, Session};

/// A value or a flag combination `read` and `write` refuse; the message names it.
#[derive(Debug, thiserror::Error)]
pub(crate) enum BadValue {
    /// `--poll`.
    #[error("'{0}' is not a poll interval: give milliseconds, at least 1 (e.g. --poll 1000 for once a second)")]
    Poll(String),
    /// An address or count.
    #[error("expected 0..=65535, decimal or 0x hex, got '{0}'")]
    Number(String),
    /// A register value.
    #[error("register value '{0}': expected 0..=65535 (decimal or 0x hex) or -32768..=-1")]
    Register(String),
    /// A coil value.
    #[error("coil value '{0}': expected 1, 0, on, off, true or false")]
    Coil(String),
    /// `--read` with coils.
    #[error("--read (FC 17) works with registers only")]
    ReadCoils,
    /// The serial port's flags.
    #[error("{0}")]
    Port(#[from] crate::config::ConfigError),
}

/// Where requests go, and how they are sent (shared by `read` and `write`).
#[derive(Debug, Clone, clap::Args)]
#[command(mut_group(PORT_GROUP, |g| g.requires("serial")))]
pub(crate) struct CommonArgs {
    /// Gateway or Modbus/TCP device, HOST[:PORT] (port 502 if left out)
    /// [default: 127.0.0.1:502]
    #[arg(long, value_name = "HOST:PORT", conflicts_with = "serial")]
    pub(crate) tcp: Option<String>,
    /// Ask a device directly on this serial port, in MBAP framing (the CIE-M10 serial
    /// Modbus/TCP mode: whole MBAP frames on the line, no CRC) unless --framing says
    /// otherwise
    #[arg(long, value_name = "PATH")]
    pub(crate) serial: Option<String>,
    /// How frames are carried: mbap, or rtu or ascii for a Modbus serial-line device on
    /// --serial, or for RTU over TCP on --tcp (a gateway's rtu listener, a serial device
    /// server in raw TCP mode)
    #[arg(long, value_parser = choice::<Framing>(), default_value = "mbap")]
    pub(crate) framing: Framing,
    /// The serial port's settings (with --serial only), as `mbgate run` takes them.
    #[command(flatten)]
    pub(crate) port: PortFlags,
    /// Unit id (slave address), 0..=255
    #[arg(long, short = 'u', value_name = "N", default_value_t = 1)]
    pub(crate) unit: u8,
    /// Give up on a reply after this long (a gateway answers 0x0B after its own
    /// response timeout, 1000 ms by default, so wait longer than that)
    #[arg(long, value_name = "MS", default_value_t = 2000,
          value_parser = clap::value_parser!(u64).range(1..=600_000))]
    pub(crate) timeout_ms: u64,
    /// Repeat every MS milliseconds until Ctrl-C (or --count), printing each result
    /// with a timestamp
    #[arg(long, value_name = "MS", value_parser = parse_poll)]
    pub(crate) poll: Option<u64>,
    /// With --poll: stop after N requests
    #[arg(long, value_name = "N", requires = "poll",
          value_parser = clap::value_parser!(u64).range(1..))]
    pub(crate) count: Option<u64>,
    /// Print both frames (request and reply) as hex
    #[arg(long, short = 'v')]
    pub(crate) verbose: bool,
}

/// The tables a master reads (docs/protocol.md §1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum ReadTable {
    /// FC 01 read coils (also: coil)
    #[value(alias = "coil")]
    Coils,
    /// FC 02 read discrete inputs (also: discrete, di)
    #[value(name = "discrete-inputs", alias = "discrete", alias = "di")]
    Discrete,
    /// FC 03 read holding registers (also: holding, hr)
    #[value(name = "holding-registers", alias = "holding", alias = "hr")]
    Holding,
    /// FC 04 read input registers (also: input, ir)
    #[value(name = "input-registers", alias = "input", alias = "ir")]
    Input,
}

/// `mbgate read`: FC 01, 02, 03 or 04.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct ReadArgs {
    #[command(flatten)]
    pub(crate) common: CommonArgs,
    /// What to read
    #[arg(value_enum)]
    pub(crate) table: ReadTable,
    /// First address: the 0-based PDU address, decimal or 0x hex (register "40108" is
    /// 107)
    #[arg(value_parser = parse_u16)]
    pub(crate) addr: u16,
    /// How many: 1..=2000 bits or 1..=125 registers
    #[arg(value_name = "COUNT", value_parser = parse_u16, default_value = "1")]
    pub(crate) quantity: u16,
}

/// The tables a master writes (docs/protocol.md §1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum WriteTable {
    /// FC 05 for one value, FC 0F for several (also: coil)
    #[value(alias = "coil")]
    Coils,
    /// FC 06 for one value, FC 10 for several, FC 17 with --read (also: holding,
    /// hr, registers, register)
    #[value(
        name = "holding-registers",
        alias = "holding",
        alias = "hr",
        alias = "registers",
        alias = "register"
    )]
    Registers,
}

/// `mbgate write`: FC 05, 06, 0F, 10 or 17.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct WriteArgs {
    #[command(flatten)]
    pub(crate) common: CommonArgs,
    /// What to write
    #[arg(value_enum)]
    pub(crate) table: WriteTable,
    /// First address: the 0-based PDU address, decimal or 0x hex
    #[arg(value_parser = parse_u16)]
    pub(crate) addr: u16,
    /// Values from ADDR on. Coils: 1, 0, on, off, true, false. Registers: 0..=65535
    /// decimal or 0x hex, or -32768..=-1 (sent as two's complement)
    #[arg(required = true, num_args = 1.., allow_negative_numbers = true)]
    pub(crate) values: Vec<String>,
    /// Use FC 0F / 10 even for a single value
    #[arg(long)]
    pub(crate) multiple: bool,
    /// FC 17 (registers only): in the same transaction, after the write, read COUNT
    /// registers at ADDR and print them
    #[arg(long, num_args = 2, value_names = ["ADDR", "COUNT"], value_parser = parse_u16,
          conflicts_with = "multiple")]
    pub(crate) read: Option<Vec<u16>>,
}

/// A poll interval: at least 1 ms; a line answers in milliseconds, so 100..=1000 is
/// what polling usually wants.
fn parse_poll(s: &str) -> Result<u64, BadValue> {
    match s.parse::<u64>() {
        Ok(ms) if ms >= 1 => Ok(ms),
        _ => Err(BadValue::Poll(s.to_owned())),
    }
}

/// `123` or `0x7B`.
fn parse_u16(s: &str) -> Result<u16, BadValue> {
    match crate::config::number::parse(s) {
        Some(v) if (0..=0xFFFF).contains(&v) => Ok(v as u16),
        _ => Err(BadValue::Number(s.to_owned())),
    }
}

/// A register value: 0..=65535, or -32768..=-1 as its two's complement.
fn parse_register(s: &str) -> Result<u16, BadValue> {
    match crate::config::number::parse(s) {
        Some(v) if (0..=0xFFFF).contains(&v) => Ok(v as u16),
        Some(v) if (-0x8000..0).contains(&v) => Ok(v as i16 as u16),
        _ => Err(BadValue::Register(s.to_owned())),
    }
}

fn parse_coil(s: &str) -> Result<bool, BadValue> {
    match s.to_ascii_lowercase().as_str() {
        "1" | "on" | "true" => Ok(true),
        "0" | "off" | "false" => Ok(false),
        _ => Err(BadValue::Coil(s.to_owned())),
    }
}

impl ReadArgs {
    /// The request these arguments ask for (docs/protocol.md §1 table, FC 01..04).
    pub(crate) fn request(&self) -> Request {
        let (addr, qty) = (self.addr, self.quantity);
        match self.table {
            ReadTable::Coils => Request::ReadCoils { addr, qty },
            ReadTable::Discrete => Request::ReadDiscreteInputs { addr, qty },
            ReadTable::Holding => Request::ReadHoldingRegisters { addr, qty },
            ReadTable::Input => Request::ReadInputRegisters { addr, qty },
        }
    }
}

impl WriteArgs {
    /// The request these arguments ask for (docs/protocol.md §1 table, FC 05, 06, 0F, 10,
    /// 17), or why there is none.
    pub(crate) fn request(&self) -> Result<Request, BadValue> {
        let addr = self.addr;
        let single = self.values.len() == 1 && !self.multiple;
        match self.table {
            WriteTable::Coils => {
                if self.read.is_some() {
                    return Err(BadValue::ReadCoils);
                }
                let values = self
                    .values
                    .iter()
                    .map(|v| parse_coil(v))
                    .collect::<Result<Vec<_>, _>>()?;
                Ok(if single {
                    Request::WriteSingleCoil {
                        addr,
                        value: values[0],
                    }
                } else {
                    Request::WriteMultipleCoils { addr, values }
                })
            }
            WriteTable::Registers => {
                let values = self
                    .values
                    .iter()
                    .map(|v| parse_register(v))
                    .collect::<Result<Vec<_>, _>>()?;
                Ok(match &self.read {
                    Some(read) => Request::ReadWriteMultipleRegisters {
                        read_addr: read[0],
                        read_qty: read[1],
                        write_addr: addr,
                        values,
                    },
                    None if single => Request::WriteSingleRegister {
                        addr,
                        value: values[0],
                    },
                    None => Request::WriteMultipleRegisters { addr, values },
                })
            }
        }
    }
}

impl CommonArgs {
    /// The session's options: the unit, the timeout, the polling and `-v`.
    pub(crate) fn session(&self) -> Session {
        Session {
            unit: self.unit,
            timeout_ms: self.timeout_ms,
            poll: self.poll,
            count: self.count,
            verbose: self.verbose,
        }
    }

    /// The transport these arguments name: `--serial` if given, else `--tcp` (default
    /// 127.0.0.1:502); or why the serial port's settings are refused.
    pub(crate) fn transport(&self) -> Result<ClientTransport, BadValue> {
        let Some(path) = &self.serial else {
            let addr = self.tcp.as_deref().unwrap_or("127.0.0.1");
            return Ok(ClientTransport::tcp_framed(addr, self.framing));
        };
        let mut cfg = SerialConfig {
            path: path.clone(),
            framing: self.framing,
            ..SerialConfig::default()
        };
        self.port.apply_serial(&mut cfg)?;
        Ok(ClientTransport::serial(cfg))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{FlowControl, Parity};

    /// The argument definitions are consistent (clap's own checks), and parse the
    /// forms docs/read-write.md documents.
    #[test]
    fn command_lines() {
        use clap::{Args, FromArgMatches};
        let read = ReadArgs::augment_args(clap::Command::new("read"));
        read.clone().debug_assert();
        let write = WriteArgs::augment_args(clap::Command::new("write"));
        write.clone().debug_assert();
        let parse_read = |args: &[&str]| {
            let m = read.clone().try_get_matches_from(args)?;
            ReadArgs::from_arg_matches(&m)
        };
        let parse_write = |args: &[&str]| {
            let m = write.clone().try_get_matches_from(args)?;
            WriteArgs::from_arg_matches(&m)
        };
        let r = parse_read(&["read", "holding", "0x6B", "3", "--unit", "17"]).unwrap();
        assert_eq!(
            r.request(),
            Request::ReadHoldingRegisters { addr: 107, qty: 3 }
        );
        assert_eq!(r.common.unit, 17);
        let r = parse_read(&[
            "read", "-v", "coil", "5", "--serial", "/dev/x", "--baud", "9600",
        ])
        .unwrap();
        assert_eq!(r.request(), Request::ReadCoils { addr: 5, qty: 1 });
        assert!(
            matches!(r.common.transport().unwrap(), ClientTransport::Serial { cfg, .. } if cfg.baud_rate == 9600)
        );
        assert!(
            matches!(r.common.transport().unwrap(), ClientTransport::Serial { cfg, .. } if cfg.framing == Framing::Mbap)
        );
        let r = parse_read(&[
            "read",
            "holding",
            "0",
            "--serial",
            "/dev/x",
            "--framing",
            "ascii",
        ])
        .unwrap();
        assert!(
            matches!(r.common.transport().unwrap(), ClientTransport::Serial { cfg, .. } if cfg.framing == Framing::Ascii)
        );
        let r = parse_read(&["read", "holding", "0", "--framing", "rtu"]).unwrap();
        assert!(
            matches!(r.common.transport().unwrap(), ClientTransport::TcpFramed { ref addr, .. } if addr == "127.0.0.1:502"),
            "RTU over TCP"
        );
        assert!(
            parse_read(&["read", "holding", "0", "--serial", "p", "--framing", "tcp"]).is_err()
        );
        assert!(
            parse_read(&["read", "holding", "0", "--baud", "9600"]).is_err(),
            "serial only"
        );
        assert!(
            parse_read(&["read", "holding", "0", "--count", "3"]).is_err(),
            "needs --poll"
        );
        assert!(parse_read(&["read", "holding", "0", "--tcp", "h", "--serial", "p"]).is_err());
        assert!(parse_read(&["read", "registers", "0"]).is_err());

        let w = parse_write(&["write", "registers", "20", "7", "8", "-1"]).unwrap();
        assert_eq!(
            w.request().ok(),
            Some(Request::WriteMultipleRegisters {
                addr: 20,
                values: vec![7, 8, 0xFFFF]
            })
        );
        let w = parse_write(&["write", "register", "8", "0x11"]).unwrap();
        assert_eq!(
            w.request().ok(),
            Some(Request::WriteSingleRegister {
                addr: 8,
                value: 0x11
            })
        );
        let w = parse_write(&["write", "register", "8", "0x11", "--multiple"]).unwrap();
        assert_eq!(
            w.request().ok(),
            Some(Request::WriteMultipleRegisters {
                addr: 8,
                values: vec![0x11]
            })
        );
        let w = parse_write(&["write", "coil", "5", "on"]).unwrap();
        assert_eq!(
            w.request().ok(),
            Some(Request::WriteSingleCoil {
                addr: 5,
                value: true
            })
        );
        let w = parse_write(&["write", "coils", "10", "1", "off", "true"]).unwrap();
        assert_eq!(
            w.request().ok(),
            Some(Request::WriteMultipleCoils {
                addr: 10,
                values: vec![true, false, true]
            })
        );
        let w = parse_write(&["write", "registers", "40", "1", "2", "--read", "39", "4"]).unwrap();
        assert_eq!(
            w.request().ok(),
            Some(Request::ReadWriteMultipleRegisters {
                read_addr: 39,
                read_qty: 4,
                write_addr: 40,
                values: vec![1, 2]
            })
        );
        let w = parse_write(&["write", "coils", "1", "1", "--read", "0", "1"]).unwrap();
        assert!(w.request().is_err());
        let w = parse_write(&["write", "coil", "1", "2"]).unwrap();
        assert!(w.request().is_err());
        assert!(
            parse_write(&["write", "coil", "1"]).is_err(),
            "a value is required"
        );
    }

    /// `--serial` takes `mbgate run`'s port flags, with their ranges; they need it.
    #[test]
    fn serial_port_flags() {
        use clap::{Args, FromArgMatches};
        let cmd = ReadArgs::augment_args(clap::Command::new("read"));
        let common = |args: &[&str]| {
            let line = ["read", "holding", "0", "--serial", "/dev/ttyS9"];
            let m = cmd
                .clone()
                .try_get_matches_from(line.iter().chain(args))
                .unwrap();
            ReadArgs::from_arg_matches(&m).unwrap().common
        };
        let args = [
            "--parity",
            "odd",
            "--stop-bits",
            "2",
            "--flow-control",
            "none",
        ];
        let Ok(ClientTransport::Serial { cfg, .. }) = common(&args).transport() else {
            panic!("a serial transport");
        };
        assert_eq!((cfg.parity, cfg.stop_bits), (Parity::Odd, 2));
        assert_eq!(
            (cfg.flow_control, cfg.baud_rate),
            (FlowControl::None, 19_200)
        );
        let bad = common(&["--stop-bits", "3"]).transport().unwrap_err();
        assert_eq!(bad.to_string(), "--stop-bits: must be 1 or 2, got 3");
        let line = ["read", "holding", "0", "--parity", "odd"];
        assert!(
            cmd.clone().try_get_matches_from(line).is_err(),
            "needs --serial"
        );
    }

    #[test]
    fn numbers() {
        assert_eq!(parse_u16("107").ok(), Some(107));
        assert_eq!(parse_u16("0x6B").ok(), Some(107));
        assert_eq!(parse_u16("0XFFFF").ok(), Some(0xFFFF));
        assert!(parse_u16("65536").is_err());
        assert!(parse_u16("-1").is_err());
        assert!(parse_u16("1e3").is_err());
        assert!(parse_u16("").is_err());
        assert_eq!(parse_register("-1").ok(), Some(0xFFFF));
        assert_eq!(parse_register("-32768").ok(), Some(0x8000));
        assert!(parse_register("-32769").is_err());
        assert_eq!(parse_register("0x0011").ok(), Some(0x11));
        assert_eq!(parse_register("65535").ok(), Some(0xFFFF));
        assert!(parse_register("+5").is_err());
        assert_eq!(parse_coil("ON").ok(), Some(true));
        assert_eq!(parse_coil("false").ok(), Some(false));
        assert!(parse_coil("2").is_err());
    }

    #[test]
    fn tcp_addresses_get_port_502() {
        let name = |s: &str| ClientTransport::tcp(s).name().to_string();
        assert_eq!(name("10.0.0.5"), "10.0.0.5:502");
        assert_eq!(name("10.0.0.5:5020"), "10.0.0.5:5020");
        assert_eq!(name("plc.local"), "plc.local:502");
        assert_eq!(name("plc.local:1502"), "plc.local:1502");
        assert_eq!(name("::1"), "[::1]:502");
        assert_eq!(name("[::1]:5020"), "[::1]:5020");
    }
}
