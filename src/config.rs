//! The configuration model of design.md §4: every key, its default, and validation.
//!
//! Loading reports errors that name the file, the line and the key (design.md §3:
//! exit code 2 on a bad configuration).

use serde::{Deserialize, Serialize};
use std::net::SocketAddr;

/// The whole file (design.md §4). Every section and key is optional; missing ones take
/// the defaults below. Unknown keys are errors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    pub serial: SerialConfig,
    pub tcp: TcpConfig,
    pub relay: RelayConfig,
    pub log: LogConfig,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Parity {
    None,
    Even,
    Odd,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FlowControl {
    Hardware,
    Software,
    None,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Framing {
    /// CIE-M10 serial Modbus/TCP: whole MBAP frames on the line (protocol.md §3).
    Mbap,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Notifications {
    Drop,
    Broadcast,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SerialConfig {
    pub path: String,
    pub baud_rate: u32,
    /// 7 or 8.
    pub data_bits: u8,
    pub parity: Parity,
    /// 1 or 2.
    pub stop_bits: u8,
    pub flow_control: FlowControl,
    pub framing: Framing,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TcpConfig {
    pub listen: SocketAddr,
    pub max_connections: usize,
    /// 0 = never close idle masters.
    pub idle_timeout_ms: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RelayConfig {
    pub response_timeout_ms: u64,
    pub frame_gap_ms: u64,
    pub max_in_flight: usize,
    pub max_pending_per_connection: usize,
    pub queue_depth: usize,
    pub retries: u32,
    pub retry_writes: bool,
    pub notifications: Notifications,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LogConfig {
    pub level: String,
    pub traffic: bool,
}

impl Default for SerialConfig {
    fn default() -> Self {
        Self {
            path: "/dev/ttyUSB0".into(),
            baud_rate: 19200,
            data_bits: 8,
            parity: Parity::None,
            stop_bits: 1,
            flow_control: FlowControl::Hardware,
            framing: Framing::Mbap,
        }
    }
}

impl Default for TcpConfig {
    fn default() -> Self {
        Self {
            listen: "0.0.0.0:502".parse().expect("valid literal"),
            max_connections: 32,
            idle_timeout_ms: 60_000,
        }
    }
}

impl Default for RelayConfig {
    fn default() -> Self {
        Self {
            response_timeout_ms: 1000,
            frame_gap_ms: 50,
            max_in_flight: 1,
            max_pending_per_connection: 16,
            queue_depth: 64,
            retries: 0,
            retry_writes: false,
            notifications: Notifications::Drop,
        }
    }
}

impl Default for LogConfig {
    fn default() -> Self {
        Self {
            level: "info".into(),
            traffic: false,
        }
    }
}

#[allow(clippy::derivable_impls)]
impl Default for Config {
    fn default() -> Self {
        Self {
            serial: SerialConfig::default(),
            tcp: TcpConfig::default(),
            relay: RelayConfig::default(),
            log: LogConfig::default(),
        }
    }
}
