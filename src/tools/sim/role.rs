//! The simulated device's role: the CIE-M10 as the master of docs/protocol.md §3
//! (`--role master --poll-ms`), or a slave (the default) that answers requests; the
//! master's timing, checked (the flags are `crate::cli`'s).

use super::options::BadFlags;
use std::time::Duration;

/// Which side of the conversation the simulated device is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Side {
    /// It answers requests (the default).
    Slave,
    /// It sends the CIE-M10 master's queries every period (cie-m10 profile).
    Master,
}

/// The role as asked: the side, and the master's period and reply timeout in ms.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Role {
    /// Which side.
    pub(crate) side: Side,
    /// The master's communication period, in ms (1000 unless asked).
    pub(crate) poll_ms: u64,
    /// How long the master waits for each reply, in ms [default: the period, at most
    /// 1000].
    pub(crate) timeout_ms: Option<u64>,
}

/// The master's timing, checked.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Polling {
    pub(crate) period: Duration,
    pub(crate) timeout: Duration,
}

impl Role {
    /// The master's timing, or why the flags do not fit together (`cie_m10`: the
    /// profile is the CIE-M10's; `listen`: the device is on the network, `--listen`).
    pub(crate) fn polling(&self, cie_m10: bool, listen: bool) -> Result<Option<Polling>, BadFlags> {
        if self.side == Side::Slave {
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
