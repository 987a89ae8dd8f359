//! The gateway as lines and listeners (docs/design.md §4.1): which units each line
//! serves and what it calls them, where its device is (a serial port or a TCP
//! address), and the listeners with their framing. The single-line form (`[serial]`,
//! `[relay]`, `[tcp]`) is one line serving every unit and one Modbus/TCP listener,
//! read into the same shape.

use super::{Config, ListenFraming, RelayConfig, SerialConfig, TcpConfig, Transport};
use std::collections::{BTreeMap, BTreeSet};

/// Which unit ids a line serves (the master's ids), and the id each has on the line.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Units {
    /// Served as they are. With `remap` also empty: every unit.
    pub ids: BTreeSet<u8>,
    /// The master's unit → the unit on the line (the master's 11 is the line's 1).
    pub remap: BTreeMap<u8, u8>,
}

impl Units {
    /// No list: the line serves every unit (the one line of the old form).
    pub(crate) fn every(&self) -> bool {
        self.ids.is_empty() && self.remap.is_empty()
    }

    /// The id the line knows the master's `unit` by, if the line serves it.
    pub(crate) fn route(&self, unit: u8) -> Option<u8> {
        if let Some(&on_line) = self.remap.get(&unit) {
            return Some(on_line);
        }
        (self.every() || self.ids.contains(&unit)).then_some(unit)
    }

    /// `ids` as the file writes them: runs of three or more as `"A-B"` strings.
    pub(crate) fn print_ids(&self) -> String {
        let ids: Vec<u8> = self.ids.iter().copied().collect();
        crate::access::rules::id_list(&ids)
    }

    /// `remap` as the file writes it: `{ 11 = 1, 12 = 2 }`.
    pub(crate) fn print_remap(&self) -> String {
        let pairs: Vec<String> = self
            .remap
            .iter()
            .map(|(m, l)| format!("{m} = {l}"))
            .collect();
        format!("{{ {} }}", pairs.join(", "))
    }
}

/// One device line: its units, its device, its queueing and timing.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct LineConfig {
    pub units: Units,
    /// The serial port's settings; on a TCP line only `framing` is read from the
    /// file (the others keep their defaults, `silence_floor_ms` ending a reply of
    /// unknown shape).
    pub serial: SerialConfig,
    /// `host:port` of a device on the network (a Modbus/TCP slave, or a serial
    /// device server in raw TCP mode) instead of the serial port.
    pub tcp: Option<String>,
    /// The device on `tcp` speaks TLS: verify it, present our certificate
    /// (docs/security.md "A device behind TLS").
    pub(crate) tcp_tls: Option<super::TlsDevice>,
    pub relay: RelayConfig,
    /// What units of the line have of their own (`[[line.unit]]`).
    pub(crate) unit_tables: super::unit::UnitTables,
    /// The line's device is the master: where its requests go (docs/design.md §4.2).
    pub master: Option<super::master::MasterLine>,
}

impl LineConfig {
    /// What the logs call the line: its serial port or its address.
    pub(crate) fn name(&self) -> &str {
        self.tcp.as_deref().unwrap_or(&self.serial.path)
    }

    /// Does `[serial]` and `[relay]` say all of this line (a serial port, every unit,
    /// none with settings of its own)? A master line's routes are its own tables.
    fn single(&self) -> bool {
        self.tcp.is_none() && self.units.every() && self.unit_tables.is_empty()
    }
}

/// One listening address and how its masters frame their requests.
#[derive(Debug, Clone, PartialEq)]
pub struct ListenConfig {
    pub tcp: TcpConfig,
    pub(crate) framing: ListenFraming,
    /// Who may connect and what they may do (docs/security.md).
    pub(crate) access: super::ListenAccess,
    /// Its masters' priority class on the lines (docs/masters.md "Priority"); a
    /// role's, if it has one, stands for it.
    pub(crate) priority: u8,
    /// TCP connections, or UDP datagrams (docs/dialing.md "Modbus over UDP").
    pub(crate) transport: super::Transport,
    /// UDP: its sources get the lines' notifications, each for [`NOTIFIED_FOR`] after
    /// its last request (docs/dialing.md "Modbus over UDP").
    pub(crate) notifications: bool,
}

/// How long after its last request a UDP source of a listener with `notifications =
/// true` gets the lines' notifications: a master that polls at least once a second
/// gets every one, and a forged datagram earns a second's worth, not a minute's
/// (docs/dialing.md "Modbus over UDP").
pub(crate) const NOTIFIED_FOR: std::time::Duration = std::time::Duration::from_secs(1);

/// The listener of `[tcp]`: Modbus/TCP, open to all, of class 0.
impl Default for ListenConfig {
    fn default() -> Self {
        ListenConfig {
            tcp: TcpConfig::default(),
            framing: ListenFraming::Mbap,
            access: super::ListenAccess::default(),
            priority: 0,
            transport: Transport::Tcp,
            notifications: false,
        }
    }
}

impl ListenConfig {
    /// Does `[tcp]` say all of this listener?
    fn single(&self) -> bool {
        self.framing == ListenFraming::Mbap
            && self.transport == Transport::Tcp
            && self.access.is_open()
            && self.priority == 0
    }
}

impl Config {
    /// Is the gateway one line that `[serial]` and `[relay]` say all of (the
    /// single-line form)? Their keys then name its settings: a flag sets them, a
    /// reload names a change by them; with `[[line]]` tables a flag could mean any.
    pub(crate) fn single_line(&self) -> bool {
        matches!(&self.lines[..], [one] if one.single())
    }

    /// Is the gateway one listener that `[tcp]` says all of?
    pub(crate) fn single_listener(&self) -> bool {
        matches!(&self.listeners[..], [one] if one.single())
    }

    /// Can the single-line form say the whole gateway (`mbgate check-config` prints
    /// it so)? A master line's routes are `[[line.route]]` tables.
    pub(crate) fn single_form(&self) -> bool {
        self.single_line() && self.single_listener() && self.lines[0].master.is_none()
    }

    /// The priority class of a master that came by `source` (a listener, or a dial),
    /// with a TLS role of `role` if any: the role's, else that of the listener of
    /// this configuration at `source`'s address and transport, else `source`'s own (a
    /// dial: a changed one dials again) (docs/masters.md "Priority").
    pub(crate) fn priority_of(&self, source: &ListenConfig, role: Option<&str>) -> u8 {
        let role = role.and_then(|name| self.roles.iter().find(|r| r.name == name));
        role.and_then(|r| r.priority).unwrap_or_else(|| {
            // The same listener as configured (two may share an address, on port 0),
            // else the one at its address and transport (a reload changed it).
            let listener = self.listeners.iter().find(|l| *l == source).or_else(|| {
                self.listeners
                    .iter()
                    .find(|l| l.tcp.listen == source.tcp.listen && l.transport == source.transport)
            });
            listener.map_or(source.priority, |l| l.priority)
        })
    }

    /// The most requests any line lets one master pipeline: the room each master's
    /// connection keeps for replies.
    pub(crate) fn max_pending_per_connection(&self) -> usize {
        let most = self
            .lines
            .iter()
            .map(|l| l.relay.max_pending_per_connection);
        most.max().unwrap_or_default()
    }

    /// The longest any line takes to answer a request it holds (its timeouts and
    /// retries): the bound of the shutdown drain.
    pub(crate) fn answer_within(&self) -> std::time::Duration {
        let longest = self.lines.iter().map(|l| match &l.master {
            // A master line's requests wait for their route's slave.
            Some(m) => m
                .routes
                .iter()
                .map(|r| std::time::Duration::from_millis(r.response_timeout_ms))
                .max()
                .unwrap_or_default(),
            None => l.unit_tables.answer_within(&l.relay),
        });
        longest.max().unwrap_or_default()
    }

    /// Is any line's device a slave, for Modbus/TCP masters to reach? Not when every
    /// line is a master line: then no listener is bound.
    pub(crate) fn serves_masters(&self) -> bool {
        self.lines.iter().any(|l| l.master.is_none())
    }

    /// Are the listeners bound? Not when no line serves masters, nor when the file
    /// only dials its masters ([`Config::dial_only`]).
    pub(crate) fn listens(&self) -> bool {
        self.serves_masters() && !self.dial_only
    }
}
