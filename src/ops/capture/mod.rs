//! Capture to pcapng (docs/capture.md; the choices in docs/design.md §6): every frame
//! each master sent and received, every frame put on and taken off each line, and the
//! bytes the gateway dropped with why, as packets Wireshark decodes as Modbus with no
//! setting. One pcapng interface for the TCP side and one per line; times in
//! microseconds from one clock.
//!
//! - `pcapng`: the file format (pure);
//! - `pcapng_read`: reading it back, from any writer (pure);
//! - `packet`: what a packet holds, and its block (pure);
//! - `tape`: which bytes a framer dropped (pure);
//! - `request`: what a capture asks for, and which packets it keeps (pure);
//! - `hub`: taps, the bounded channel and the task that hands packets on;
//! - `ring`: the always-on ring of files (`[capture] file`).
//!
//! A capture is asked for over the control socket (`crate::gateway::control`: the gateway's
//! end, and `mbgate capture`).

pub(crate) mod dropped;
pub(crate) mod hub;
pub(crate) mod packet;
pub mod pcapng;
pub mod pcapng_read;
pub(crate) mod request;
pub(crate) mod ring;

use crate::config::{Config, ListenFraming};
pub(crate) use hub::{Hub, Interface, Tap};

/// The interfaces of a gateway of `cfg`: the TCP side (0), then each line.
pub(crate) fn interfaces(cfg: &Config) -> Vec<Interface> {
    let mut v = Vec::new();
    // The TCP side: the masters' listeners, and the slaves of each master line.
    let mut said = Vec::new();
    if cfg.listens() {
        let listeners: Vec<String> = cfg
            .listeners
            .iter()
            .map(|l| match l.framing {
                ListenFraming::Mbap => l.tcp.listen.to_string(),
                ListenFraming::Rtu => format!("{} (RTU over TCP)", l.tcp.listen),
            })
            .collect();
        said.push(format!("Modbus/TCP masters on {}", listeners.join(", ")));
    }
    let routes = cfg.lines.iter().filter_map(|l| l.master.as_ref());
    let routes: Vec<String> = routes
        .flat_map(|m| m.routes.iter().map(|r| r.peer.to_string()))
        .collect();
    if !routes.is_empty() {
        said.push(format!(
            "Modbus/TCP slaves of the master line: {}",
            routes.join(", ")
        ));
    }
    v.push(Interface {
        name: "tcp".into(),
        description: said.join("; "),
    });
    for (i, line) in cfg.lines.iter().enumerate() {
        let device = match &line.tcp {
            Some(addr) => format!("device at {addr}"),
            None => format!(
                "{} baud {}",
                line.serial.baud_rate,
                crate::config::describe::char_format(&line.serial)
            ),
        };
        let role = if line.master.is_some() {
            ", the device is the master"
        } else {
            ""
        };
        v.push(Interface {
            name: line.name().to_owned(),
            description: format!("line {i}: {}, {device}{role}", line.serial.framing.name()),
        });
    }
    v
}

/// How long a stopping gateway waits for its captures to write their end.
const END_WITHIN: std::time::Duration = std::time::Duration::from_millis(500);

/// The capture of a running gateway: its hub and its ring.
pub(crate) struct Capture {
    hub: Hub,
    ring: Option<std::thread::JoinHandle<()>>,
}

impl Capture {
    /// Starts the hub for `cfg`'s interfaces and the ring (if `capture.file` is set).
    /// The control socket, where captures are asked for, is `crate::gateway::control`'s.
    pub(crate) fn start(cfg: &Config) -> Capture {
        let (hub, task) = Hub::new(interfaces(cfg));
        tokio::spawn(task);
        let ring = ring::start(&cfg.capture, &hub);
        Capture { hub, ring }
    }

    pub(crate) fn hub(&self) -> &Hub {
        &self.hub
    }

    /// After the last packet: every capture ends, the ring's files are flushed.
    pub(crate) async fn finish(self) {
        self.hub.close();
        // A capture running now gets its last packets and its end before the
        // process exits; one that does not read is not waited for long.
        if !self.hub.ended(END_WITHIN).await {
            tracing::debug!("a capture did not end within {END_WITHIN:?}");
        }
        if let Some(ring) = self.ring {
            let _ = tokio::task::spawn_blocking(move || ring.join()).await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A line's interface names its framing, speed and character format (a replay
    /// takes the wire's time at it: docs/simulator.md "Replaying a device"); a device
    /// on the network, its address.
    #[test]
    fn a_line_s_interface_says_its_speed_and_character_format() {
        let text = "[[line]]\nunits = [1]\nserial = { path = \"/dev/ttyUSB0\", framing = \"rtu\", baud_rate = 19200, parity = \"even\" }\n\
                    [[line]]\nunits = [2]\nserial = { path = \"/dev/ttyUSB1\", framing = \"ascii\", baud_rate = 9600, data_bits = 7, stop_bits = 2 }\n\
                    [[line]]\ntcp = { address = \"10.0.0.5:502\" }\nunits = [9]\n";
        let cfg = crate::config::parse(text, "test.toml").unwrap();
        let said: Vec<String> = interfaces(&cfg)
            .into_iter()
            .skip(1)
            .map(|i| i.description)
            .collect();
        assert_eq!(
            said,
            [
                "line 0: rtu, 19200 baud 8E1",
                "line 1: ascii, 9600 baud 7N2",
                "line 2: mbap, device at 10.0.0.5:502"
            ]
        );
    }
}
