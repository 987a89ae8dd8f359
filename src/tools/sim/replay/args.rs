//! `mbgate sim --replay`'s flags (docs/simulator.md "Replaying a device").

use std::path::PathBuf;

/// A recorded device instead of a profile.
#[derive(Debug, Clone, Default, clap::Args)]
pub(crate) struct ReplayArgs {
    /// Replay the devices a capture of `mbgate capture` (or its `[capture] file`
    /// ring) recorded on the gateway's lines, instead of a profile. Repeat for
    /// several files (a ring, several days): where they disagree, the latest wins.
    /// The profiles' flags do not apply.
    #[arg(
        long,
        value_name = "FILE.pcapng",
        help_heading = "replay",
        conflicts_with_all = [
            "profile", "unit", "input_address", "output_address", "loopback", "notify",
            "toggle_ms", "units", "fill", "coils", "registers", "role",
        ]
    )]
    pub(crate) replay: Vec<PathBuf>,
    /// Play the values back over time as they were recorded (from the capture's
    /// start, at its pace; the last value after its end), rather than the last seen.
    #[arg(long, requires = "replay", help_heading = "replay")]
    pub(crate) timeline: bool,
    /// The exception for an address the capture never saw read (02, illegal data
    /// address, by default).
    #[arg(
        long,
        value_name = "CODE",
        default_value_t = 2,
        value_parser = clap::value_parser!(u8).range(1..=255),
        help_heading = "replay"
    )]
    pub(crate) unknown_exception: u8,
    /// Refuse every write, with the exception the device gave to a write if the
    /// capture has one, else 01 (illegal function). Without it, writes change the
    /// replayed values.
    #[arg(long, requires = "replay", help_heading = "replay")]
    pub(crate) read_only: bool,
    /// Say what the files hold, unit by unit, and exit.
    #[arg(long, requires = "replay", help_heading = "replay")]
    pub(crate) summary: bool,
}

impl ReplayArgs {
    /// The choices for what the capture does not say.
    pub(crate) fn choices(&self) -> super::Choices {
        super::Choices {
            unknown: self.unknown_exception,
            read_only: self.read_only,
            timeline: self.timeline,
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::cli::sim::SimArgs;
    use clap::Parser;

    #[derive(Parser)]
    struct S {
        #[command(flatten)]
        s: SimArgs,
    }

    fn parse(args: &[&str]) -> Result<SimArgs, clap::Error> {
        S::try_parse_from(std::iter::once("t").chain(args.iter().copied())).map(|s| s.s)
    }

    #[test]
    fn the_replay_flags_go_with_replay_and_the_summary_needs_no_port() {
        let s = parse(&["--replay", "a.pcapng", "--replay", "b.pcapng", "--summary"]).unwrap();
        assert_eq!(s.replay.replay.len(), 2);
        let c = s.replay.choices();
        assert_eq!((c.unknown, c.read_only, c.timeline), (2, false, false));
        let s = parse(&[
            "--replay",
            "a.pcapng",
            "--serial",
            "/dev/ttyS0",
            "--timeline",
            "--read-only",
            "--unknown-exception",
            "11",
        ])
        .unwrap();
        let c = s.replay.choices();
        assert_eq!((c.unknown, c.read_only, c.timeline), (11, true, true));
        for alone in ["--timeline", "--read-only", "--summary"] {
            let e = parse(&["--serial", "/dev/ttyS0", alone])
                .unwrap_err()
                .to_string();
            assert!(e.contains("--replay"), "{alone}: {e}");
        }
        let e = parse(&["--replay", "a", "--summary", "--unknown-exception", "0"])
            .unwrap_err()
            .to_string();
        assert!(e.contains("0 is not in 1..=255"), "{e}");
        let e = parse(&["--replay", "a", "--summary", "--profile", "generic"])
            .unwrap_err()
            .to_string();
        assert!(e.contains("cannot be used with"), "{e}");
        // A file that is not there: the flag and the file named.
        let e = parse(&["--replay", "/nonexistent/a.pcapng", "--summary"])
            .unwrap()
            .settings()
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("--replay /nonexistent/a.pcapng: No such file"),
            "{e}"
        );
    }
}
