//! The gateway as lines and listeners (docs/design.md §4.1): which units each line
//! serves and what it calls them, where its device is (a serial port or a TCP
//! address), and the listeners with their framing. The old form (`[serial]`,
//! `[relay]`, `[tcp]`) is one line serving every unit and one Modbus/TCP listener.

use super::{Config, ListenFraming, RelayConfig, SerialConfig, TcpConfig};
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
        crate::number::id_list(&ids)
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
    pub tcp_tls: Option<super::TlsDevice>,
    pub relay: RelayConfig,
    /// What units of the line have of their own (`[[line.unit]]`).
    pub unit_tables: super::unit::UnitTables,
    /// The line's device is the master: where its requests go (docs/design.md §4.2).
    pub(crate) master: Option<super::master::MasterLine>,
}

impl LineConfig {
    /// What the logs call the line: its serial port or its address.
    pub(crate) fn name(&self) -> &str {
        self.tcp.as_deref().unwrap_or(&self.serial.path)
    }
}

/// One listening address and how its masters frame their requests.
#[derive(Debug, Clone, PartialEq)]
pub struct ListenConfig {
    pub(crate) tcp: TcpConfig,
    pub(crate) framing: ListenFraming,
    /// Who may connect and what they may do (docs/security.md).
    pub(crate) access: super::ListenAccess,
    /// Its masters' priority class on the lines (docs/masters.md "Priority"); a
    /// role's, if it has one, stands for it.
    pub(crate) priority: u8,
    /// TCP connections, or UDP datagrams (docs/dialing.md "Modbus over UDP").
    pub(crate) transport: super::Transport,
}

impl Config {
    /// The lines mbgate runs: the `[[line]]` tables, or the one line of `[serial]` and
    /// `[relay]` that serves every unit.
    pub fn lines(&self) -> Vec<LineConfig> {
        if !self.lines.is_empty() {
            return self.lines.clone();
        }
        vec![LineConfig {
            units: Units::default(),
            serial: self.serial.clone(),
            tcp: None,
            tcp_tls: None,
            relay: self.relay.clone(),
            unit_tables: Default::default(),
            master: self.master.clone(),
        }]
    }

    /// The listeners mbgate runs: the `[[listen]]` tables, or the one Modbus/TCP
    /// listener of `[tcp]`.
    pub fn listeners(&self) -> Vec<ListenConfig> {
        if !self.listeners.is_empty() {
            return self.listeners.clone();
        }
        vec![ListenConfig {
            tcp: self.tcp.clone(),
            framing: ListenFraming::Mbap,
            access: super::ListenAccess::default(),
            priority: 0,
            transport: super::Transport::Tcp,
        }]
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
        let lines = self.lines();
        let most = lines.iter().map(|l| l.relay.max_pending_per_connection);
        most.max().unwrap_or(self.relay.max_pending_per_connection)
    }

    /// The longest any line takes to answer a request it holds (its timeouts and
    /// retries): the bound of the shutdown drain.
    pub(crate) fn answer_within(&self) -> std::time::Duration {
        let lines = self.lines();
        let longest = lines.iter().map(|l| match &l.master {
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
        self.lines().iter().any(|l| l.master.is_none())
    }
}
