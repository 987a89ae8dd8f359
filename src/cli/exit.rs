//! Every exit code of `mbgate`, in one place (docs/design.md §3): what each subcommand
//! returns and when. The subcommands' rooms return typed outcomes and errors; only
//! `cli` turns them into these numbers.
//!
//! | Subcommand | 0 | 1 | 2 | 3 |
//! |---|---|---|---|---|
//! | `run` | stopped by a signal | failed while running | bad configuration or flags | |
//! | `check-config` | valid | | not valid | |
//! | `read`, `write` | a normal response | no answer | bad arguments | an exception response |
//! | `sim`, `demo` | stopped by a signal | failed while running | bad flags | |
//! | `scan` | something answered | nothing did, or the port could not be used | bad arguments | |
//! | `wire` | stopped by a signal | failed | bad arguments | |
//! | `status` | healthy | not healthy | bad arguments | the gateway could not be asked |
//! | `capture` | ended as asked | could not run, or its output failed | bad arguments | |
//! | `reload` | taken | refused | bad arguments | the gateway could not be asked |
//! | `generate` | written | could not write | bad arguments | |
//! | `hash-password` | printed | the passwords differ, or none | bad arguments | |
//!
//! clap exits 2 on arguments it refuses itself, so every "bad arguments" is 2.

use std::process::ExitCode;

/// Done as asked.
pub(crate) const OK: u8 = 0;
/// Failed; for `read`/`write` no answer, `scan` nothing answered, `status` not
/// healthy, `reload` refused.
pub(crate) const FAILED: u8 = 1;
/// Bad arguments, flags or configuration (clap uses 2 too).
pub(crate) const USAGE: u8 = 2;
/// `read`/`write`: an exception response; `status`, `reload`: the gateway could not
/// be asked.
pub(crate) const OTHER: u8 = 3;

/// The exit code `code`.
pub(crate) fn code(code: u8) -> ExitCode {
    ExitCode::from(code)
}

/// `mbgate: {message}` on stderr, then exit 2.
pub(crate) fn usage(message: impl std::fmt::Display) -> ExitCode {
    eprintln!("mbgate: {message}");
    code(USAGE)
}

/// `mbgate: {message}` on stderr, then exit 1.
pub(crate) fn failed(message: impl std::fmt::Display) -> ExitCode {
    eprintln!("mbgate: {message}");
    code(FAILED)
}

/// Exit 0 when `yes`, else 1.
pub(crate) fn ok_if(yes: bool) -> ExitCode {
    code(if yes { OK } else { FAILED })
}

/// An error and each of its sources, `outer: inner: ...`, as a one-line message. A
/// source the message says already (an error whose text has its `{source}` in it, as
/// thiserror lets it) is not said again.
pub(crate) fn said(e: &(dyn std::error::Error + 'static)) -> String {
    let mut out = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let text = s.to_string();
        if !out.contains(&text) {
            out += ": ";
            out += &text;
        }
        source = s.source();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, thiserror::Error)]
    #[error("cannot link x: {source}")]
    struct Says {
        source: std::io::Error,
    }

    #[derive(Debug, thiserror::Error)]
    #[error("cannot listen")]
    struct Leaves {
        source: std::io::Error,
    }

    /// Each source once: after a message that leaves it out, and never twice after
    /// one that says it.
    #[test]
    fn each_source_is_said_once() {
        let gone = || std::io::Error::from(std::io::ErrorKind::NotFound);
        assert_eq!(
            said(&Says { source: gone() }),
            "cannot link x: entity not found"
        );
        assert_eq!(
            said(&Leaves { source: gone() }),
            "cannot listen: entity not found"
        );
    }
}
