//! Reading capture files into a [`Replay`]: each file read whole (a damaged one up to
//! its damage, with a warning), the requests of all of them applied in time order so
//! the latest wins, and the summary of what each unit's map is known to hold
//! (docs/simulator.md "Replaying a device").

use super::learn::{observations, Observation};
use super::model::{Model, ReplayOutcome};
use super::{Choices, Replay};
use crate::ops::capture::pcapng_read;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// A file that cannot be replayed.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// It could not be read.
    #[error("--replay {path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        error: std::io::Error,
    },
    /// It is no pcapng file.
    #[error("--replay {path}: refused {damage}")]
    Refused {
        /// The file.
        path: PathBuf,
        /// Where and why.
        damage: pcapng_read::Damage,
    },
    /// The files hold no request a device answered or let time out on a line.
    #[error(
        "--replay {0}: no Modbus request on any line (a capture of `mbgate capture` \
         or `[capture] file` holds the lines' frames)"
    )]
    Empty(String),
}

/// What one file adds: its requests, and a warning if it was read only in part.
fn file(path: &Path) -> Result<(Vec<Observation>, Option<String>), LoadError> {
    let bytes = std::fs::read(path).map_err(|error| LoadError::Io {
        path: path.to_owned(),
        error,
    })?;
    let read = pcapng_read::read(&bytes).map_err(|damage| LoadError::Refused {
        path: path.to_owned(),
        damage,
    })?;
    let warning = read.damage.as_ref().map(|d| {
        format!(
            "--replay {}: read up to byte {} of {} and no further: {} ({} packets before it used)",
            path.display(),
            d.offset,
            bytes.len(),
            d.reason,
            read.packets.len()
        )
    });
    Ok((observations(&read), warning))
}

/// Reads `paths` into a replay with `choices`; `seed` seeds the delays' draw.
pub fn load(paths: &[PathBuf], choices: Choices, seed: u64) -> Result<Replay, LoadError> {
    let mut all = Vec::new();
    let mut warnings = Vec::new();
    for path in paths {
        let (seen, warning) = file(path)?;
        all.extend(seen);
        warnings.extend(warning);
    }
    // Stable: within one moment, the order of the files and lines.
    all.sort_by_key(|o| o.at_us);
    let mut model = Model::default();
    for o in &all {
        model.apply(o);
    }
    if model.units.is_empty() {
        let names: Vec<String> = paths.iter().map(|p| p.display().to_string()).collect();
        return Err(LoadError::Empty(names.join(", ")));
    }
    let summary = summary(&model, paths.len(), all.len(), &choices);
    Ok(Replay {
        model,
        choices,
        started: std::time::Instant::now(),
        rng: fastrand::Rng::with_seed(seed),
        summary,
        warnings,
    })
}

/// What the files hold: one line for the whole, one per unit, one for the choices.
fn summary(m: &Model, files: usize, requests: usize, c: &Choices) -> String {
    let span = m
        .end_us
        .unwrap_or(0)
        .saturating_sub(m.start_us.unwrap_or(0));
    let mut s = format!(
        "replaying {} unit{} from {files} file{}: {requests} requests over {:.1} s",
        m.units.len(),
        if m.units.len() == 1 { "" } else { "s" },
        if files == 1 { "" } else { "s" },
        span as f64 / 1e6
    );
    for (id, u) in &m.units {
        let known = u.known();
        let known = if known.is_empty() {
            "no value known".to_string()
        } else {
            known.join(", ")
        };
        let count =
            |f: fn(&ReplayOutcome) -> bool| u.outcomes.values().filter(|(_, o)| f(o)).count();
        let exceptions = count(|o| matches!(o, ReplayOutcome::Exception(_)));
        let silent = count(|o| *o == ReplayOutcome::Silent);
        let framing = u.framing.map_or("?", |f| f.name());
        let _ = write!(
            s,
            "\nunit {id} ({framing}): {known}; {exceptions} request{} answered with an exception, {silent} unanswered",
            if exceptions == 1 { "" } else { "s" },
        );
        match (u.quantile_us(0.5), u.quantile_us(0.9)) {
            (Some(p50), Some(p90)) => {
                let _ = write!(
                    s,
                    "; reply time p50 {:.2} ms, p90 {:.2} ms ({} replies)",
                    p50 as f64 / 1e3,
                    p90 as f64 / 1e3,
                    u.turnarounds_us.len()
                );
            }
            _ => s.push_str("; no reply time"),
        }
    }
    let _ = write!(
        s,
        "\nnever read: exception {:02X}; writes: {}; values: {}",
        c.unknown,
        if c.read_only {
            "refused"
        } else {
            "change the values"
        },
        if c.timeline {
            "over time (--timeline)"
        } else {
            "the last seen"
        }
    );
    s
}
