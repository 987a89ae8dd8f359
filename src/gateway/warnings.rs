//! What a configuration asks that a line cannot honour (an RTU or ASCII line's
//! in-flight depth, hardware flow control, broadcast notifications): said at start and
//! by `mbgate check-config`, not refused.

use crate::config::{Config, FlowControl, Framing, LineConfig, Notifications};
use tracing::warn;

/// What the configuration cannot honour on this line ([`warnings`]), said once at start.
pub(super) fn warn_inapplicable(cfg: &Config) {
    for warning in warnings(cfg) {
        warn!("{warning}");
    }
}

/// Settings an RTU or ASCII line cannot honour: said at start (and by `mbgate
/// check-config`), not refused, so a file written for MBAP keeps working when only the
/// framing changes. With several lines each is named (`line[1]: ...`).
pub(crate) fn warnings(cfg: &Config) -> Vec<String> {
    let lines = &cfg.lines;
    let mut said = Vec::new();
    for (i, line) in lines.iter().enumerate() {
        let name = if lines.len() > 1 {
            format!("line[{i}]: ")
        } else {
            String::new()
        };
        said.extend(
            line_warnings(line)
                .into_iter()
                .map(|w| format!("{name}{w}")),
        );
    }
    said
}

fn line_warnings(line: &LineConfig) -> Vec<String> {
    let framing = line.serial.framing.name();
    let mut said = Vec::new();
    if line.serial.framing == Framing::Mbap {
        return said;
    }
    if line.relay.max_in_flight > 1 {
        said.push(format!(
            "framing = {framing} has no transaction id: one request at a time \
             (max_in_flight = {} taken as 1)",
            line.relay.max_in_flight
        ));
    }
    if line.tcp.is_none() && line.serial.flow_control == FlowControl::Hardware {
        said.push(format!(
            "framing = {framing} with flow_control = hardware (the default, for the CIE-M10's \
             RS-232 link): RS-485 adapters and most {} devices do not wire RTS/CTS, and an \
             adapter whose CTS is never raised holds every request back (0x0B for each); \
             set flow_control = \"none\" unless the cable carries RTS and CTS",
            framing.to_uppercase()
        ));
    }
    if line.relay.notifications == Notifications::Broadcast {
        said.push(format!(
            "framing = {framing}: a frame that answers no request is dropped; \
             notifications = broadcast does not apply"
        ));
    }
    said
}
