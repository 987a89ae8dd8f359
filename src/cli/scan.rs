//! `mbgate scan` (docs/scan.md): exit 0 something answered, 1 nothing did or the port
//! could not be used (held by a gateway: the process is named), 2 bad arguments.
//! Ctrl-C ends it with what was found so far.

use super::exit;
use super::signals::{self, Stops};
use crate::tools::scan::probe::{SerialFraming, UnitList};
use crate::tools::scan::{scan, ScanError, ScanOptions};
use crate::tools::wire::uart::Format;
use std::process::ExitCode;

/// `mbgate scan`'s flags.
#[derive(Debug, clap::Args)]
pub(crate) struct ScanArgs {
    /// The serial port (or a virtual line's end) to scan.
    #[arg(value_name = "PORT", required_unless_present = "tcp")]
    port: Option<String>,
    /// Scan a Modbus/TCP device or gateway at HOST:PORT instead: unit ids only.
    #[arg(long, value_name = "HOST:PORT", conflicts_with = "port")]
    tcp: Option<String>,
    /// The baud rates to try, in order [default: 19200,9600,115200,38400,57600,4800,2400,1200]
    #[arg(long, value_delimiter = ',', value_name = "BAUD,...")]
    baud: Vec<u32>,
    /// The formats to try, in order [default: 8E1,8N1,8N2,8O1]
    #[arg(long, value_delimiter = ',', value_name = "FORMAT,...")]
    format: Vec<Format>,
    /// The framings to try, in order [default: rtu,ascii]
    #[arg(long, value_delimiter = ',', value_name = "FRAMING,...")]
    framing: Vec<SerialFraming>,
    /// The unit ids to try: ids and ranges, `1-247`, `1,2,10-20`.
    #[arg(long, default_value = "1-247", value_name = "IDS")]
    units: UnitList,
    /// How long a device may take to answer, beyond the request's and the reply's own
    /// time on the wire (a later reply still counts, in the next units' time).
    #[arg(long, default_value_t = 50, value_name = "MS")]
    timeout_ms: u64,
    /// Leave a setting after this many units got no frame with a good CRC or LRC (a
    /// setting that got one is scanned to the last unit; so are 19200 and 9600 baud,
    /// 8E1 and 8N1, RTU and ASCII, the settings most buses use).
    #[arg(long, default_value_t = 3, value_name = "N")]
    give_up: usize,
    /// Go on to the other settings after one is found (a bus has one setting, so by
    /// default the scan ends with the first that answers).
    #[arg(long)]
    all: bool,
    /// Send nothing: listen to a live bus at each setting in turn and report the
    /// setting, units, function codes, request rate and reply times heard.
    #[arg(long, conflicts_with = "tcp")]
    listen: bool,
    /// With --listen: how long to listen at each setting.
    #[arg(long, default_value_t = 3.0, value_name = "SECONDS")]
    listen_secs: f64,
    /// Print the result as JSON instead of a table.
    #[arg(long)]
    json: bool,
}

impl ScanArgs {
    /// The options the scan runs with.
    fn options(self) -> ScanOptions {
        ScanOptions {
            port: self.port,
            tcp: self.tcp,
            baud: self.baud,
            format: self.format,
            framing: self.framing,
            units: self.units,
            timeout_ms: self.timeout_ms,
            give_up: self.give_up,
            all: self.all,
            listen: self.listen,
            listen_secs: self.listen_secs,
            json: self.json,
        }
    }
}

/// `mbgate scan`.
pub(crate) fn main(args: ScanArgs) -> ExitCode {
    let rt = match signals::runtime(exit::FAILED) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    let options = args.options();
    let scanned = rt.block_on(async { scan(&options, signals::stop_on(Stops::Interrupt)).await });
    match scanned {
        Ok(s) => {
            let (text, found) = s.said(&options);
            print!("{text}");
            exit::ok_if(found)
        }
        Err(ScanError::Option(e)) => exit::usage(e),
        Err(e) => exit::failed(e),
    }
}
