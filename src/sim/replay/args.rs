//! `mbgate sim --replay`'s flags (docs/simulator.md "Replaying a device").

use std::path::PathBuf;

/// A recorded device instead of a profile.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ReplayArgs {
    /// Replay the devices a capture of `mbgate capture` (or its `[capture] file`
    /// ring) recorded on the gateway's lines, instead of a profile. Repeat for
    /// several files (a ring, several days): where they disagree, the latest wins.
    #[arg(long, value_name = "FILE.pcapng", help_heading = "replay")]
    pub replay: Vec<PathBuf>,
    /// Play the values back over time as they were recorded (from the capture's
    /// start, at its pace; the last value after its end), rather than the last seen.
    #[arg(long, requires = "replay", help_heading = "replay")]
    pub timeline: bool,
    /// The exception for an address the capture never saw read (02, illegal data
    /// address, by default).
    #[arg(
        long,
        value_name = "CODE",
        default_value_t = 2,
        value_parser = clap::value_parser!(u8).range(1..=255),
        help_heading = "replay"
    )]
    pub unknown_exception: u8,
    /// Refuse every write, with the exception the device gave to a write if the
    /// capture has one, else 01 (illegal function). Without it, writes change the
    /// replayed values.
    #[arg(long, requires = "replay", help_heading = "replay")]
    pub read_only: bool,
    /// Say what the files hold, unit by unit, and exit.
    #[arg(long, requires = "replay", help_heading = "replay")]
    pub summary: bool,
}

impl ReplayArgs {
    /// The choices for what the capture does not say.
    pub fn choices(&self) -> super::Choices {
        super::Choices {
            unknown: self.unknown_exception,
            read_only: self.read_only,
            timeline: self.timeline,
        }
    }
}
