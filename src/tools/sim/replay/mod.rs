//! `mbgate sim --replay FILE.pcapng`: a device played back from what `mbgate capture`
//! recorded of it (docs/simulator.md "Replaying a device").
//!
//! - `learn` pairs each request on a line with the reply or timeout it got (pure);
//! - `model` keeps what each unit held, answered and took to answer (pure);
//! - `answer` answers a request from the model (pure, time passed in);
//! - `load` reads the files, merges them and says what they hold;
//! - [`args`] is the command line.

mod answer;
pub(crate) mod args;
mod learn;
mod load;
mod model;

pub(crate) use answer::Choices;
pub(crate) use load::load;

use super::Answer;
use std::time::{Duration, Instant};

/// Logs what a replayed device's files hold and any damage in them, and starts its
/// timeline: the simulator is about to serve it.
pub(crate) fn announce(device: &mut super::Device) {
    if let super::Profile::Replay(r) = &mut device.profile {
        for w in &r.warnings {
            tracing::warn!("{w}");
        }
        for line in r.summary.lines() {
            tracing::info!("{line}");
        }
        r.restart_clock();
    }
}

/// The replayed devices: the model, the choices, and the replay's own clock and dice.
#[derive(Debug, Clone)]
pub struct Replay {
    model: model::Model,
    choices: Choices,
    /// When the replay started: a `--timeline` replay is this far into the capture.
    started: Instant,
    /// Draws each reply's delay from the unit's recorded ones.
    rng: fastrand::Rng,
    /// What the files hold, unit by unit (`--summary`, the log at start, `list`).
    pub(crate) summary: String,
    /// Files read only up to their damage, and why.
    pub(crate) warnings: Vec<String>,
}

impl PartialEq for Replay {
    fn eq(&self, other: &Self) -> bool {
        self.model == other.model && self.choices == other.choices
    }
}

impl Eq for Replay {}

impl Replay {
    /// The unit ids replayed.
    pub(crate) fn units(&self) -> Vec<u8> {
        self.model.units.keys().copied().collect()
    }

    /// How the first unit's line carried its frames, if the capture says.
    pub(crate) fn framing(&self) -> Option<crate::config::Framing> {
        self.model.units.values().find_map(|u| u.framing)
    }

    /// The timeline starts now (when serving starts, not when the files were read).
    pub(crate) fn restart_clock(&mut self) {
        self.started = Instant::now();
    }

    /// Answers one request as the device did, after a delay drawn from its own times
    /// (`learn::own_times`).
    pub(crate) fn answer(&mut self, unit: u8, pdu: &[u8]) -> Answer {
        let moment = self.choices.timeline.then(|| {
            let elapsed = self.started.elapsed().as_micros() as u64;
            self.model.start_us.unwrap_or(0).saturating_add(elapsed)
        });
        let reply = self.model.answer(unit, pdu, moment, &self.choices);
        // The device's own times for this very request, else any of the unit's: the
        // simulator counts the delay from the request's last byte in (src/tools/sim/serve/mod.rs).
        let times = self
            .model
            .units
            .get(&unit)
            .map(|u| u.own_by_request.get(pdu).map_or(&u.own_us[..], |t| &t[..]));
        let delay = match (&reply, times) {
            (Some(_), Some(t)) if !t.is_empty() => Some(Duration::from_micros(u64::from(
                t[self.rng.usize(..t.len())],
            ))),
            _ => None,
        };
        Answer {
            reply,
            notification: None,
            delay,
        }
    }

    /// A broadcast (unit 0 on a bus): every unit takes a write, none answers.
    pub(crate) fn broadcast(&mut self, pdu: &[u8]) {
        for unit in self.units() {
            if model::is_write(pdu.first().copied().unwrap_or(0)) {
                let _ = self.model.answer(unit, pdu, None, &self.choices);
            }
        }
    }
}
