//! Reading capture files into a [`Replay`]: each file streamed one block at a time (a
//! damaged one up to its damage, with a warning), each request applied to the model
//! as it comes (the model keeps what it saw with its time, so the latest wins
//! whatever the order), and the summary of what each unit's map is known to hold
//! (docs/simulator.md "Replaying a device"). A file of any size takes the memory of
//! its largest block and of the model, never of the file.

use super::learn::Learner;
use super::model::{Model, ReplayOutcome};
use super::{Choices, Replay};
use crate::ops::capture::pcapng_read::{self, Blocks, Unreadable, BLOCK_HEAD};
use std::fmt::Write as _;
use std::io::Read as _;
use std::path::{Path, PathBuf};

/// A file that cannot be replayed.
#[derive(Debug, thiserror::Error)]
pub(crate) enum LoadError {
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
    /// The files hold no request a device answered or let time out on a line; where
    /// a file was damaged, why it was read no further.
    #[error(
        "--replay {files}: no Modbus request on any line (a capture of `mbgate capture` \
         or `[capture] file` holds the lines' frames){}",
        damage.iter().map(|d| format!("; {d}")).collect::<String>()
    )]
    Empty {
        /// The files, as named.
        files: String,
        /// Each damaged file's warning.
        damage: Vec<String>,
    },
}

/// Applies what one file holds to `model`, its lines numbered from `*lines` on (which
/// moves past them): how many requests it held, and a warning if it was read only in
/// part. Read one block at a time.
fn file(
    path: &Path,
    model: &mut Model,
    lines: &mut usize,
) -> Result<(usize, Option<String>), LoadError> {
    let io = |error| LoadError::Io {
        path: path.to_owned(),
        error,
    };
    let f = std::fs::File::open(path).map_err(io)?;
    let size = f.metadata().map_err(io)?.len();
    let mut rd = std::io::BufReader::with_capacity(1 << 16, f);
    let mut blocks = Blocks::default();
    let mut learner = Learner::new(*lines);
    let mut block = Vec::new();
    let (mut packets, mut requests) = (0usize, 0usize);
    let damage = loop {
        match next_block(&mut rd, &mut blocks, &mut block).map_err(io)? {
            Ok(true) => {}
            Ok(false) => break None,
            Err(d) => break Some(d),
        }
        match blocks.block(&block) {
            Ok(None) => {}
            Ok(Some(p)) => {
                packets += 1;
                if let Some(o) = learner.packet(&blocks.interfaces, &p) {
                    model.apply(&o);
                    requests += 1;
                }
            }
            Err(d) => break Some(d),
        }
    };
    *lines += blocks.interfaces.len();
    if let Some(d) = damage.as_ref().filter(|d| Blocks::refuses(d)) {
        return Err(LoadError::Refused {
            path: path.to_owned(),
            damage: d.clone(),
        });
    }
    let warning = damage.map(|d| {
        format!(
            "--replay {}: read up to byte {} of {size} and no further: {} ({packets} packets before it used)",
            path.display(),
            d.offset,
            d.reason,
        )
    });
    Ok((requests, warning))
}

/// The next block of `rd` into `block`: whether there was one (none at the file's
/// end), or the damage that ends the reading.
fn next_block(
    rd: &mut impl std::io::Read,
    blocks: &mut Blocks,
    block: &mut Vec<u8>,
) -> std::io::Result<Result<bool, pcapng_read::Damage>> {
    block.clear();
    // The block's head, then the rest of it as long as the file has it: a length
    // a damaged file claims is never allocated before its bytes are there.
    rd.by_ref().take(BLOCK_HEAD as u64).read_to_end(block)?;
    if block.is_empty() {
        return Ok(Ok(false));
    }
    let total = match blocks.length(block) {
        Ok(total) => total,
        Err(d) => return Ok(Err(d)),
    };
    rd.by_ref()
        .take((total - block.len()) as u64)
        .read_to_end(block)?;
    if block.len() < total {
        return Ok(Err(blocks.damage(Unreadable::Truncated)));
    }
    Ok(Ok(true))
}

/// Reads `paths` into a replay with `choices`; `seed` seeds the delays' draw.
pub(crate) fn load(paths: &[PathBuf], choices: Choices, seed: u64) -> Result<Replay, LoadError> {
    let mut model = Model::new(choices.timeline);
    let mut warnings = Vec::new();
    let (mut requests, mut lines) = (0, 0);
    for path in paths {
        let (n, warning) = file(path, &mut model, &mut lines)?;
        requests += n;
        warnings.extend(warning);
    }
    if model.units.is_empty() {
        let names: Vec<String> = paths.iter().map(|p| p.display().to_string()).collect();
        return Err(LoadError::Empty {
            files: names.join(", "),
            damage: warnings,
        });
    }
    model.finish();
    let summary = summary(&model, paths.len(), requests, &choices);
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
