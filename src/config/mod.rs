//! The configuration model of docs/design.md §4: every setting declared once, below.
//!
//! Each setting is one line of `settings!`: key, type, default, allowed values, flag
//! and help. From it come the section structs and their defaults, and [`KEYS`], which
//! the file reader ([`file`]), `check-config`, the flags (`crate::cli::overrides`) and
//! the tests holding docs/configuration.md and `config/mbgate.toml` to it all read. A value is
//! checked the same way from the file or a flag. A new setting is one line here plus
//! what it does. The keys of a table inside a line or a listener (`[[line.route]]`,
//! `[[line.unit]]`, a listener's security keys...) are declared the same way, one line
//! of [`table!`] each, beside what reads them; ranges two keys share are one [`Check`].

pub mod access;
mod conflict;
pub(crate) mod describe;
pub mod dial;
mod error;
mod file;
mod layout;
pub mod master;
pub(crate) mod number;
mod print;
mod raw;
pub(crate) mod unit;
mod value;

pub(crate) use access::{AccessRole, ListenAccess, TlsDevice, TlsListen};

/// Who may connect to `listen` and what they may do, in words (the start-up log,
/// `mbgate check-config`).
pub(crate) fn effective_access(listen: &ListenConfig, roles: &[AccessRole]) -> Vec<String> {
    let said = access::effective(&listen.access, roles);
    match listen.transport {
        Transport::Tcp => said,
        // A datagram's source is whatever its sender wrote (docs/security.md).
        Transport::Udp => said
            .into_iter()
            .map(|s| s.replace("plain TCP", "UDP, source addresses unauthenticated"))
            .collect(),
    }
}
pub use error::ConfigError;
pub(crate) use error::{Step, ValueError};
pub use file::{load, parse, LINE_TCP_KEYS};
pub(crate) use file::{read_text, MAX_FILE};
pub(crate) use layout::{LineConfig, ListenConfig, Units, NOTIFIED_FOR};
pub use print::{to_toml, to_toml_lines};
pub use raw::Raw;
use std::net::SocketAddr;
pub use unit::UNIT_KEYS;
pub(crate) use value::HostPort;
pub(crate) use value::{
    parse_listen, parse_optional_address, Check, Setting, ValueKind, METRICS_EXAMPLE,
};
pub use value::{Floor, GpioLine};
use Check::{Address, Any, NonEmpty, OneOf, Range, SocketPath};

/// Declares enums whose values are lower-case words in the file and on the command
/// line; each variant's doc line is its help.
macro_rules! choices {
    ($($(#[doc = $doc:literal])* $Enum:ident {
        $($(#[doc = $vdoc:literal])* $V:ident = $name:literal,)*
    })*) => {$(
        $(#[doc = $doc])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        pub enum $Enum { $($(#[doc = $vdoc])* #[doc = concat!("\n\nWritten `", $name, "`.")] $V,)* }

        impl $Enum {
            /// The word for this value in the file.
            pub(crate) fn name(self) -> &'static str {
                match self { $(Self::$V => $name,)* }
            }
        }

        impl Setting for $Enum {
            const KIND: ValueKind = ValueKind::Choice(&[$(($name, concat!("", $($vdoc),*))),*]);
            fn read(raw: &Raw, _: &Check) -> Result<Self, ValueError> {
                let names = [$($name),*].join(", ");
                match raw {
                    $(Raw::Str(s) if s == $name => Ok(Self::$V),)*
                    Raw::Str(s) => Err(format!("invalid value {s:?}; expected one of {names}").into()),
                    _ => Err(format!("expected a string, one of {names}").into()),
                }
            }
            fn print(&self) -> String {
                format!("\"{}\"", self.name())
            }
        }
    )*};
}

choices! {
    /// The serial line's parity bit.
    Parity { None = "none", Even = "even", Odd = "odd", }
    /// How the serial line holds off a sender whose receiver is full.
    FlowControl {
        /// RTS/CTS, as the device manual advises
        Hardware = "hardware",
        /// XON/XOFF
        Software = "software",
        None = "none",
    }
    /// How Modbus frames are carried on the line (docs/protocol.md).
    Framing {
        /// CIE-M10 serial Modbus/TCP: whole MBAP frames on the line (docs/protocol.md §3)
        Mbap = "mbap",
        /// Modbus RTU: unit, PDU, CRC-16; one transaction at a time
        Rtu = "rtu",
        /// Modbus ASCII: `:`, hex, LRC, CR LF; one transaction at a time
        Ascii = "ascii",
    }
    /// What a master that sent a broadcast (unit 0) gets back (Modbus over Serial Line
    /// V1.02 §2.1: the device answers no broadcast).
    BroadcastReply {
        /// The master gets nothing back (as on the bus)
        None = "none",
        /// The master gets the reply the device would have given
        Echo = "echo",
    }
    /// What becomes of frames from the device that answer no request (docs/protocol.md §3).
    Notifications {
        /// Frames from the device that answer no request are dropped and counted
        Drop = "drop",
        /// Well-formed unsolicited frames go to every connected master
        Broadcast = "broadcast",
    }
    /// What the serial port is, for the rules that read the clock against `baud_rate`
    /// (docs/reliability.md "Knowing the wire").
    PortKind {
        /// Learnt at each open: a pseudo-terminal has no wire; a UART, a USB adapter or any other port is a wire at baud_rate
        Auto = "auto",
        /// No wire whatever the port (a pty, a virtual port): a reply is taken however soon it comes
        Pty = "pty",
        /// A wire at baud_rate whatever the port (a pty in front of a real line): echoes and replies begun before the request left are dropped
        Wire = "wire",
    }
    /// Who switches an RS-485 transmitter on to send and off to receive (docs/rs485.md).
    Direction {
        /// The gateway switches nothing: the adapter does it by itself, or the kernel does (rs485 = true)
        None = "none",
        /// The gateway asserts RTS while it sends (TIOCMBIS, TIOCMBIC): DE wired to RTS, a driver without RS-485 mode
        Rts = "rts",
        /// The gateway drives a GPIO line while it sends (the GPIO character device): DE wired to a GPIO pin
        Gpio = "gpio",
    }
    /// Which end of a line the device is (docs/design.md §4.2).
    LineRole {
        /// The device answers: masters on TCP reach it through the line
        Slave = "slave",
        /// The device asks: its requests go out by the line's [[line.route]] tables
        Master = "master",
    }
    /// How masters frame their requests on a listener (docs/design.md §4.1).
    ListenFraming {
        /// Modbus/TCP: an MBAP header, many requests in flight
        Mbap = "mbap",
        /// RTU over TCP: unit, PDU, CRC-16, one request at a time
        Rtu = "rtu",
    }
    /// How a listener's masters reach it (docs/dialing.md "Modbus over UDP").
    Transport {
        /// TCP connections, one master each
        Tcp = "tcp",
        /// UDP datagrams, one MBAP request each, answered to their source
        Udp = "udp",
    }
}

impl Framing {
    /// The framer for a line of this framing (the framings themselves are
    /// `crate::frame`'s, which knows nothing of the configuration).
    pub(crate) fn framer(self) -> crate::frame::framer::Framer {
        use crate::frame::{framer::Framer, serial::Codec};
        match self {
            Framing::Mbap => Framer::mbap(),
            Framing::Rtu => Framer::serial(Codec::Rtu),
            Framing::Ascii => Framer::serial(Codec::Ascii),
        }
    }
}

/// The values `log.level` accepts.
pub(crate) const LOG_LEVELS: [&str; 5] = ["trace", "debug", "info", "warn", "error"];

/// The struct of a section or a table as [`settings!`] and [`table!`] declare it: its
/// keys as public fields, and its default from theirs.
macro_rules! declared_struct {
    ($(#[doc = $sdoc:literal])* $Struct:ident {$(
        $(#[doc = $doc:literal])* $key:ident: $ty:ty = $default:expr;
    )*}) => {
        $(#[doc = $sdoc])*
        #[derive(Debug, Clone, PartialEq)]
        pub struct $Struct { $($(#[doc = $doc])* pub $key: $ty,)* }

        impl Default for $Struct {
            fn default() -> Self {
                Self { $($key: $default,)* }
            }
        }
    };
}
pub(crate) use declared_struct;

/// Where a section's keys are in a [`Config`]: `[serial]` and `[relay]` are the one
/// line's (the first line's, of a configuration of several), `[tcp]` the one
/// listener's; the others are the gateway's own.
macro_rules! section {
    ($c:expr, serial) => {
        $c.lines[0].serial
    };
    ($c:expr, relay) => {
        $c.lines[0].relay
    };
    ($c:expr, tcp) => {
        $c.listeners[0].tcp
    };
    ($c:expr, $section:ident) => {
        $c.$section
    };
}

/// The gateway as it runs (docs/design.md §4, §4.1): its lines and its listeners,
/// whichever form the file wrote them in, and the gateway's own sections. The
/// single-line form (`[serial]`, `[relay]`, `[tcp]`) is one line serving every unit
/// and one Modbus/TCP listener open to all, from the moment the file is read: no
/// setting is kept twice, and every reader reads `lines` and `listeners`.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    /// Never empty: one line serving every unit when the file says no `[[line]]`.
    pub lines: Vec<LineConfig>,
    /// Never empty: the one Modbus/TCP listener of `[tcp]` when the file says no
    /// `[[listen]]` (bound only if some line serves masters, and the file is not
    /// [`Config::dial_only`]).
    pub listeners: Vec<ListenConfig>,
    /// The `[[role]]` tables: what a TLS master may do, by the role its
    /// certificate carries (docs/security.md).
    pub(crate) roles: Vec<AccessRole>,
    /// The `[[dial]]` tables: masters mbgate connects to (docs/dialing.md).
    pub(crate) dials: Vec<dial::DialConfig>,
    /// The file dials its masters and says no `[tcp]` nor `[[listen]]` (nor does a
    /// `--listen` flag): no listener is bound, so a gateway that reaches its SCADA
    /// server by dialing opens no port (docs/dialing.md "No listener").
    pub(crate) dial_only: bool,
    /// What is logged.
    pub log: LogConfig,
    /// The metrics listener (docs/watching.md).
    pub metrics: MetricsConfig,
    /// The always-on capture (docs/capture.md).
    pub(crate) capture: CaptureConfig,
    /// The control socket (docs/capture.md).
    pub(crate) control: ControlConfig,
}

/// The file with no key: one line and one listener, every setting its default.
impl Default for Config {
    fn default() -> Self {
        Config {
            lines: vec![LineConfig::default()],
            listeners: vec![ListenConfig::default()],
            roles: Vec::new(),
            dials: Vec::new(),
            dial_only: false,
            log: LogConfig::default(),
            metrics: MetricsConfig::default(),
            capture: CaptureConfig::default(),
            control: ControlConfig::default(),
        }
    }
}

/// Declares the sections and their settings: `key: type = default, check, "flag"
/// "VALUE_NAME" [port] [master] [, at_most other: "why"];` under the key's one line of
/// help. `port` marks the serial port settings that `mbgate sim` and the client take as
/// flags too; `master` a `[serial]` or `[relay]` key that a master line uses too (the
/// others mean nothing there, and are refused on one); `at_most` refuses a value above that of
/// another key of the section. The tables inside a line or a listener are declared
/// the same way by [`table!`], beside what reads them (`master.rs`, `access.rs`).
macro_rules! settings {
    ($($(#[doc = $sdoc:literal])* [$section:ident] $Struct:ident {$(
        $(#[doc = $doc:literal])*
        $key:ident: $ty:ty = $default:expr, $check:expr, $flag:literal $vname:literal $($mark:ident)*
            $(, at_most $other:ident: $why:literal)?;
    )*})*) => {
        $(
            $crate::config::declared_struct! {
                $(#[doc = $sdoc])* $Struct { $($(#[doc = $doc])* $key: $ty = $default;)* }
            }
        )*

        /// Every setting, in the order of the file.
        pub static KEYS: &[Key] = &[$($(Key {
            section: stringify!($section),
            name: stringify!($key),
            flag: $flag,
            value_name: $vname,
            help: concat!("", $($doc),*),
            check: $check,
            kind: <$ty as Setting>::KIND,
            port: settings!(@port $($mark)*),
            master: settings!(@master $($mark)*),
            at_most: settings!(@at_most $($other $why)?),
            set: |c, raw| {
                section!(c, $section).$key = Setting::read(raw, &$check)?;
                Ok(())
            },
            get: |c| section!(c, $section).$key.print(),
        },)*)*];
    };
    (@port) => { false };
    (@port port $($m:ident)*) => { true };
    (@port $m:ident $($more:ident)*) => { settings!(@port $($more)*) };
    (@master) => { false };
    (@master master $($m:ident)*) => { true };
    (@master $m:ident $($more:ident)*) => { settings!(@master $($more)*) };
    (@at_most) => { None };
    (@at_most $other:ident $why:literal) => { Some((stringify!($other), $why)) };
}

/// Declares a table inside a line or a listener (a `[[line.route]]`, a listener's
/// `tls`...) as [`settings!`] declares a section: `key: type = default, check;` under
/// the key's one line of help. From it come the table's struct and its default, and
/// its [`Key`]s, by which `raw::read_table` reads such a table of the file and the
/// tests hold docs/configuration.md to it.
macro_rules! table {
    ($(#[doc = $sdoc:literal])* [$path:literal] $Struct:ident $KEYS:ident {$(
        $(#[doc = $doc:literal])*
        $key:ident: $ty:ty = $default:expr, $check:expr;
    )*}) => {
        $crate::config::declared_struct! {
            $(#[doc = $sdoc])* $Struct { $($(#[doc = $doc])* $key: $ty = $default;)* }
        }

        #[doc = concat!("The keys of `", $path, "`, in the order of docs/configuration.md.")]
        pub static $KEYS: &[Key<$Struct>] = &[$(Key {
            section: $path,
            name: stringify!($key),
            flag: "",
            value_name: "",
            help: concat!("", $($doc),*),
            check: $check,
            kind: <$ty as Setting>::KIND,
            port: false,
            master: false,
            at_most: None,
            set: |c, raw| {
                c.$key = Setting::read(raw, &$check)?;
                Ok(())
            },
            get: |c| c.$key.print(),
        },)*];
    };
}
pub(crate) use table;

/// The fastest `serial.baud_rate` there is: what the demos set a pty to, since it
/// passes bytes at once.
pub(crate) const FASTEST_BAUD: u32 = 4_000_000;

settings! {
    /// The serial line to the device.
    [serial] SerialConfig {
        /// Serial device of the Modbus device
        path: String = "/dev/ttyUSB0".into(), NonEmpty("the serial device, e.g. /dev/ttyUSB0"), "serial" "PATH" master;
        /// Serial speed in bit/s
        baud_rate: u32 = 19_200, Range(50, FASTEST_BAUD as i128, None), "baud" "N" port master;
        /// Data bits
        data_bits: u8 = 8, Range(7, 8, Some("7 or 8")), "data-bits" "N" port master;
        /// Parity
        parity: Parity = Parity::None, Any, "parity" "PARITY" port master;
        /// Stop bits
        stop_bits: u8 = 1, Range(1, 2, Some("1 or 2")), "stop-bits" "N" port master;
        /// Serial flow control
        flow_control: FlowControl = FlowControl::Hardware, Any, "flow-control" "FLOW_CONTROL" port master;
        /// Serial framing
        framing: Framing = Framing::Mbap, Any, "framing" "FRAMING" master;
        /// What the port is: auto (learnt at each open), pty (no wire) or wire (a wire at baud_rate)
        port_kind: PortKind = PortKind::Auto, Any, "port-kind" "PORT_KIND";
        /// Turn the driver's low latency on at each open (TIOCSSERIAL ASYNC_LOW_LATENCY, what setserial low_latency does; an FTDI adapter then hands bytes over every 1 ms)
        low_latency: bool = true, Any, "low-latency" "BOOL" master;
        /// Least silence that ends a frame (RTU: a reply of unknown shape; MBAP: confirms a held reply); "auto": from the port (a pty 0, a UART its FIFO, a USB adapter its latency timer + 2)
        silence_floor_ms: Floor = Floor::Auto, Range(0, 1000, Some("\"auto\" or 0 to 1000")), "silence-floor-ms" "MS" master;
        /// RTU/ASCII: silence before each request, in microseconds; 0 is the specification's (RTU: 3.5 characters, 1750 above 19 200 baud; ASCII: none after a whole reply)
        inter_frame_gap_us: u64 = 0, Range(0, 1_000_000, None), "inter-frame-gap-us" "US";
        /// Turn on the kernel's RS-485 mode (TIOCSRS485): RTS drives the transmitter
        rs485: bool = false, Any, "rs485" "BOOL" master;
        /// RS-485: RTS delay before sending
        rs485_delay_before_send_ms: u32 = 0, Range(0, 1000, None), "rs485-delay-before-send-ms" "MS" master;
        /// RS-485: RTS delay after sending
        rs485_delay_after_send_ms: u32 = 0, Range(0, 1000, None), "rs485-delay-after-send-ms" "MS" master;
        /// The adapter echoes what is sent: read it back and discard it
        echo: bool = false, Any, "echo" "BOOL";
        /// RS-485: who switches the transmitter: none (the adapter, or the kernel with rs485 = true), rts or gpio (the gateway; RTU/ASCII lines)
        direction: Direction = Direction::None, Any, "direction" "DIRECTION";
        /// direction: the opposite level switches the transmitter on (RTS released, the GPIO line low while sending)
        direction_invert: bool = false, Any, "direction-invert" "BOOL";
        /// direction = "gpio": the GPIO chip by path (/dev/gpiochip0), name (gpiochip0) or label; "" (the default): gpiochip0, or for a line given by name, every chip
        direction_gpio_chip: String = String::new(), Any, "direction-gpio-chip" "CHIP";
        /// direction = "gpio": the line by offset on its chip (17) or by name ("GPIO17")
        direction_gpio_line: GpioLine = GpioLine::Unset, Any, "direction-gpio-line" "LINE";
        /// direction: microseconds between switching the transmitter on and the first byte
        direction_delay_before_us: u32 = 0, Range(0, 1_000_000, None), "direction-delay-before-us" "US";
        /// direction: microseconds between the last stop bit leaving and switching the transmitter off
        direction_delay_after_us: u32 = 0, Range(0, 1_000_000, None), "direction-delay-after-us" "US";
    }
    /// Where Modbus/TCP masters connect.
    [tcp] TcpConfig {
        /// TCP address to listen on for Modbus/TCP masters
        listen: SocketAddr = SocketAddr::from(([0, 0, 0, 0], 502)), Any, "listen" "ADDR";
        /// Simultaneous master connections
        max_connections: usize = 32, Range(1, 4096, None), "max-connections" "N";
        /// Close a master connection idle this long
        idle_timeout_ms: u64 = 60_000, Range(0, u64::MAX as i128, Some("0 (never) or a number of milliseconds")), "idle-timeout-ms" "MS";
    }
    /// How requests are queued, sent and answered on the line.
    [relay] RelayConfig {
        /// Time to wait for the device's reply
        response_timeout_ms: u64 = 1000, TIMEOUT_MS, "response-timeout-ms" "MS";
        /// Silence after which a partial serial frame is discarded (MBAP: and a held reply taken while other replies are due)
        frame_gap_ms: u64 = 50, Range(1, 60_000, None), "frame-gap-ms" "MS" master;
        /// Requests outstanding on the serial line at once
        max_in_flight: usize = 1, IN_FLIGHT, "max-in-flight" "N";
        /// Queued requests per master connection
        max_pending_per_connection: usize = 16, Range(1, 1024, None), "max-pending-per-connection" "N",
            at_most queue_depth: "one master could pipeline more than the whole queue holds";
        /// Total queued requests
        queue_depth: usize = 64, Range(1, 65_536, None), "queue-depth" "N";
        /// Resends after a timeout (reads only unless --retry-writes)
        retries: u32 = 0, RETRIES, "retries" "N";
        /// Also resend writes after a timeout (a resent write may act twice)
        retry_writes: bool = false, Any, "retry-writes" "BOOL";
        /// What to do with device frames that answer no request
        notifications: Notifications = Notifications::Drop, Any, "notifications" "NOTIFICATIONS";
        /// MBAP: the device sends frames nobody asked for (the CIE-M10's input port change notification; off as shipped): every reply is then held for confirmation
        device_notifications: bool = false, Any, "device-notifications" "BOOL";
        /// RTU/ASCII: quiet time after a broadcast (unit 0)
        broadcast_delay_ms: u64 = 100, Range(0, 60_000, None), "broadcast-delay-ms" "MS";
        /// RTU/ASCII: what a master gets for a broadcast
        broadcast_reply: BroadcastReply = BroadcastReply::None, Any, "broadcast-reply" "BROADCAST_REPLY";
        /// RTU/ASCII: back off units that keep timing out
        unit_backoff: bool = true, Any, "unit-backoff" "BOOL";
        /// Timeouts in a row that back a unit off
        unit_backoff_after: u32 = 3, Range(1, 100, None), "unit-backoff-after" "N";
        /// First back-off interval
        unit_backoff_ms: u64 = 1000, Range(1, 3_600_000, None), "unit-backoff-ms" "MS",
            at_most unit_backoff_max_ms: "the first backoff would be longer than the longest";
        /// Longest back-off interval
        unit_backoff_max_ms: u64 = 30_000, Range(1, 3_600_000, None), "unit-backoff-max-ms" "MS";
        /// RTU/ASCII: response timeout of a request probing a backed-off unit
        probe_timeout_ms: u64 = 250, TIMEOUT_MS, "probe-timeout-ms" "MS";
        /// RTU/ASCII: quiet time after a timeout, late replies discarded
        timeout_guard_ms: u64 = 100, Range(0, 60_000, None), "timeout-guard-ms" "MS";
        /// A read identical to one waiting for the line (unit, function, address, count) joins it: one transaction, each master answered
        coalesce: bool = true, Any, "coalesce" "BOOL";
        /// Answer a read from the reply to the identical read if younger than this; a write to the unit clears it; 0 = off
        cache_ms: u64 = 0, Range(0, 3_600_000, None), "cache-ms" "MS";
        /// Quiet time after each reply before the next request, for slow devices
        request_pause_ms: u64 = 0, PAUSE_MS, "request-pause-ms" "MS";
    }
    /// What is logged.
    [log] LogConfig {
        /// Log level (RUST_LOG overrides)
        level: String = "info".into(), OneOf(&LOG_LEVELS), "log-level" "LEVEL";
        /// Log every whole frame at debug level: direction, connection, unit, both transaction ids, function, address and count, hex
        traffic: bool = false, Any, "traffic" "BOOL";
    }
    /// The metrics listener (docs/watching.md): off unless given an address.
    [metrics] MetricsConfig {
        /// Address for Prometheus metrics (/metrics) and the status page; "" (the default): none
        listen: Option<SocketAddr> = None, Address(METRICS_EXAMPLE), "metrics-listen" "ADDR";
        /// The metrics listener's web configuration file, in the format of Prometheus' exporter-toolkit (TLS, client certificates, users with bcrypt hashes: docs/watching.md); "" (the default): plain HTTP, no users
        web_config: String = String::new(), Any, "metrics-web-config" "FILE";
    }
    /// The always-on capture (docs/capture.md): every packet into a ring of pcapng files.
    [capture] CaptureConfig {
        /// Always-on capture to pcapng: the current file of a ring, the older ones FILE.1 to FILE.N-1; "" (the default): off
        file: String = String::new(), Any, "capture-file" "FILE";
        /// Files in the capture ring, the current one included
        files: u32 = 10, Range(2, 1000, None), "capture-files" "N";
        /// Size of each file of the capture ring, in kB (1024 bytes)
        file_size_kb: u64 = 10_240, Range(16, 16_777_216, None), "capture-file-size-kb" "KB";
    }
    /// The control socket `mbgate capture` uses (docs/capture.md).
    [control] ControlConfig {
        /// Unix socket for mbgate capture, mode 0660 (root, the service's user and group); "" (the default): control.sock in systemd's RuntimeDirectory, none outside systemd
        socket: String = String::new(), SocketPath, "control-socket" "PATH";
    }
}

/// A response timeout in milliseconds: of a line, of a probe, of a unit, of a master
/// line's route.
const TIMEOUT_MS: Check = Range(1, 600_000, None);
/// Requests outstanding at once: on a line, on a master line's route.
const IN_FLIGHT: Check = Range(1, 255, None);
/// Quiet time before the next request: of a line, of a unit.
const PAUSE_MS: Check = Range(0, 60_000, None);
/// Resends after a timeout: of a line, of a unit.
const RETRIES: Check = Range(0, 10, None);

/// One setting as declared in `settings!` (`C` the configuration it sets), or in
/// `table!` (`C` that table's struct).
#[derive(Debug)]
pub struct Key<C: 'static = Config> {
    /// The section it is in: `serial` for `serial.baud_rate`; for a key of a table
    /// inside a line or a listener, that table (`line.route`).
    pub section: &'static str,
    /// The key within its section: `baud_rate`.
    pub name: &'static str,
    /// The long flag without its dashes: `baud` for `--baud`; "" for a key of a table
    /// inside a line or a listener, which has none.
    pub flag: &'static str,
    pub(crate) value_name: &'static str,
    /// One line (with a leading space, as doc comments have it).
    pub help: &'static str,
    pub(crate) check: Check,
    pub(crate) kind: ValueKind,
    /// A serial port setting that `mbgate sim` and the client take as flags too.
    pub(crate) port: bool,
    /// A `[serial]` or `[relay]` key a master line uses too (the others are refused on
    /// one).
    pub(crate) master: bool,
    /// The key of the section this one must not exceed, and why.
    pub(crate) at_most: Option<(&'static str, &'static str)>,
    /// Checks a value and sets this key in a configuration; the error says why,
    /// without the key.
    pub(crate) set: fn(&mut C, &Raw) -> Result<(), ValueError>,
    /// The value of this key in a configuration, as written in a TOML file (a
    /// `[serial]` or `[relay]` key: the first line's; a `[tcp]` key: the first
    /// listener's).
    pub get: fn(&C) -> String,
}
