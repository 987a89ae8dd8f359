//! `mbgate sim`'s role flags: the CIE-M10 as the master of docs/protocol.md §3
//! (`--role master --poll-ms`); a slave (the default) answers requests.

use std::time::Duration;

/// Which side of the conversation the simulated device is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum Side {
    /// It answers requests (the default).
    Slave,
    /// It sends the CIE-M10 master's queries every --poll-ms (cie-m10 profile).
    Master,
}

#[derive(Debug, Clone, clap::Args)]
pub struct RoleArgs {
    /// slave answers requests; master sends, every --poll-ms, FC 03 for the slave's
    /// input port register and FC 16 with its own inputs to the slave's output port
    /// register (the --input-address and --output-address), and sets its outputs from
    /// what it read.
    #[arg(long, value_enum, default_value_t = Side::Slave, help_heading = "role")]
    pub(crate) role: Side,
    /// master: the communication period, in ms.
    #[arg(long, default_value_t = 1000, value_name = "MS", help_heading = "role")]
    pub(crate) poll_ms: u64,
    /// master: how long it waits for each reply, in ms [default: the period, at most 1000].
    #[arg(long, value_name = "MS", help_heading = "role")]
    pub(crate) timeout_ms: Option<u64>,
}

/// The master's timing, checked.
#[derive(Debug, Clone, Copy)]
pub struct Polling {
    pub(crate) period: Duration,
    pub(crate) timeout: Duration,
}

impl RoleArgs {
    /// The master's timing, or why the flags do not fit together (`listen`: the
    /// device is on the network, `--listen`).
    pub fn polling(
        &self,
        cie_m10: bool,
        listen: bool,
    ) -> Result<Option<Polling>, super::options::BadFlags> {
        if self.role == Side::Slave {
            if self.timeout_ms.is_some() || self.poll_ms != 1000 {
                return Err("--poll-ms and --timeout-ms apply to --role master".into());
            }
            return Ok(None);
        }
        if !cie_m10 {
            return Err("--role master is the cie-m10 profile's".into());
        }
        if listen {
            return Err("--role master sends on a serial port (--serial), not --listen".into());
        }
        if self.poll_ms == 0 || self.timeout_ms == Some(0) {
            return Err("--poll-ms and --timeout-ms must be positive".into());
        }
        let period = Duration::from_millis(self.poll_ms);
        let timeout = self
            .timeout_ms
            .map_or(period.min(Duration::from_secs(1)), Duration::from_millis);
        Ok(Some(Polling { period, timeout }))
    }
}
