//! Where the log goes: stderr, as tracing's usual lines (time, level, target), or, when
//! stderr is systemd's journal stream, one `<N>message fields` line per event: the
//! syslog priority prefix of sd-daemon(3), which journald turns into the entry's
//! priority (so `journalctl -p warning` shows warnings), and no timestamp (journald
//! keeps its own) nor colours.

use crate::config::LogConfig;
use std::fmt;
use std::os::fd::AsFd;
use std::os::unix::fs::MetadataExt;
use std::sync::OnceLock;
use tracing::{Event, Level, Subscriber};
use tracing_subscriber::fmt::format::Writer;
use tracing_subscriber::fmt::{FmtContext, FormatEvent, FormatFields};
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::registry::LookupSpan;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::{reload, EnvFilter, Registry};

/// The filter of the installed subscriber, replaced by a reload ([`reload`]).
static FILTER: OnceLock<reload::Handle<EnvFilter, Registry>> = OnceLock::new();

/// What `cfg` asks to be logged: `cfg.level` (or `RUST_LOG`), and the traffic log.
fn filter(cfg: &LogConfig) -> EnvFilter {
    let mut filter = match std::env::var("RUST_LOG") {
        Ok(s) if !s.is_empty() => EnvFilter::new(s),
        _ => EnvFilter::new(&cfg.level),
    };
    if cfg.traffic {
        filter = filter.add_directive("mbgate::traffic=debug".parse().expect("valid directive"));
    }
    filter
}

/// Installs the global subscriber: `cfg.level` (or `RUST_LOG`), the traffic log if
/// asked for, and the journald format when stderr is the journal.
pub(crate) fn init(cfg: &LogConfig) {
    let (filter, handle) = reload::Layer::new(filter(cfg));
    let _ = FILTER.set(handle);
    let fmt = tracing_subscriber::fmt::layer().with_writer(std::io::stderr);
    let registry = tracing_subscriber::registry().with(filter);
    if stderr_is_journal() {
        registry
            .with(fmt.with_ansi(false).event_format(Journal))
            .init();
    } else {
        let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
        registry.with(fmt.with_ansi(ansi)).init();
    }
}

/// Applies `cfg`'s level and traffic log to the running subscriber (a reload); does
/// nothing when [`init`] did not install it (tests in process).
pub(crate) fn reload(cfg: &LogConfig) {
    if let Some(handle) = FILTER.get() {
        let _ = handle.reload(filter(cfg));
    }
}

/// `<3>` when stderr is the journal, else nothing: for the lines `main` writes itself
/// (errors at start, before or instead of the subscriber).
pub(crate) fn error_prefix() -> &'static str {
    if stderr_is_journal() {
        "<3>"
    } else {
        ""
    }
}

/// Is stderr the stream systemd connected to the journal? `JOURNAL_STREAM` holds its
/// `device:inode` (systemd.exec(5)); comparing with stderr itself ignores a variable
/// inherited by a process whose stderr was redirected elsewhere.
pub(crate) fn stderr_is_journal() -> bool {
    let Some(var) = std::env::var_os("JOURNAL_STREAM") else {
        return false;
    };
    let Ok(fd) = std::io::stderr().as_fd().try_clone_to_owned() else {
        return false;
    };
    let Ok(meta) = std::fs::File::from(fd).metadata() else {
        return false;
    };
    var.to_str()
        .is_some_and(|v| names_stream(v, meta.dev(), meta.ino()))
}

/// Does a `JOURNAL_STREAM` value name this device and inode?
fn names_stream(var: &str, dev: u64, ino: u64) -> bool {
    let Some((d, i)) = var.split_once(':') else {
        return false;
    };
    d.parse() == Ok(dev) && i.parse() == Ok(ino)
}

/// The syslog priority journald files an event under (sd-daemon(3)): error 3, warning
/// 4, info 6, debug and trace 7.
pub(crate) fn syslog_priority(level: &Level) -> u8 {
    match *level {
        Level::ERROR => 3,
        Level::WARN => 4,
        Level::INFO => 6,
        _ => 7,
    }
}

/// `<N>message key=value ...`: the journald line format.
struct Journal;

impl<S, N> FormatEvent<S, N> for Journal
where
    S: Subscriber + for<'a> LookupSpan<'a>,
    N: for<'a> FormatFields<'a> + 'static,
{
    fn format_event(
        &self,
        ctx: &FmtContext<'_, S, N>,
        mut writer: Writer<'_>,
        event: &Event<'_>,
    ) -> fmt::Result {
        write!(writer, "<{}>", syslog_priority(event.metadata().level()))?;
        ctx.field_format().format_fields(writer.by_ref(), event)?;
        writeln!(writer)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn journal_stream_must_name_this_device_and_inode() {
        assert!(names_stream("8:1234", 8, 1234));
        assert!(!names_stream("8:1235", 8, 1234));
        assert!(!names_stream("9:1234", 8, 1234));
        for bad in ["", "8", "8:", ":1234", "8:1234:5", "x:y", "8 :1234"] {
            assert!(!names_stream(bad, 8, 1234), "{bad:?}");
        }
    }

    #[test]
    fn levels_map_to_syslog_priorities() {
        assert_eq!(syslog_priority(&Level::ERROR), 3);
        assert_eq!(syslog_priority(&Level::WARN), 4);
        assert_eq!(syslog_priority(&Level::INFO), 6);
        assert_eq!(syslog_priority(&Level::DEBUG), 7);
        assert_eq!(syslog_priority(&Level::TRACE), 7);
    }
}
