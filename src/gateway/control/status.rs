//! `mbgate status` over the control socket: asks the running gateway for its metrics
//! (the words `status`, then `ok` and the exposition, `control/mod.rs`), so a check on
//! the gateway's own machine needs no password and no metrics listener; the summary
//! is made from them as from `/metrics` (`crate::ops::metrics::status_command`).

use super::{ask, NoAnswer, STATUS};
use std::path::Path;
use std::time::Duration;

/// The metrics of the gateway serving the control socket at `socket`, as its
/// `/metrics` has them; `Err(why)` inside when it answered with an error.
pub(crate) fn metrics(socket: &Path) -> Result<Result<String, String>, NoAnswer> {
    let answer = ask(socket, STATUS, Duration::from_secs(10))?;
    Ok(match answer.split_once('\n') {
        Some(("ok", text)) => Ok(text.to_owned()),
        _ => Err(answer
            .trim_end()
            .strip_prefix("error: ")
            .unwrap_or(answer.trim_end())
            .to_owned()),
    })
}
