//! The simulated device's flags (shared by `mbgate sim` and `mbgate demo`) and their
//! validation into [`Settings`]; `mbgate sim`'s own flags are `crate::cli`'s.

use super::cie_m10::CieM10;
use super::line::{ChunkMode, Chunker, Faults};
use super::replay::args::ReplayArgs;
use super::{generic, Device, Profile};
use crate::config::Framing;
use std::time::Duration;

/// The device `mbgate sim --profile` simulates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum ProfileName {
    /// The Sollae CIE-M10/H10 of docs/protocol.md §3: 8 inputs, 8 outputs, FC 03 and 16.
    #[value(name = "cie-m10")]
    CieM10,
    /// Devices by unit id with all four tables, FC 01-06, 0F, 10, 17.
    Generic,
}

/// What generic devices' holding registers start at.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum Fill {
    Zero,
    Address,
    /// Pieces of MBAP headers (`generic::HEADER_FILL`, repeating every 12 registers):
    /// replies that spell frames, to put a gateway's decoder to the test.
    Header,
}

/// Which direction the line faults hit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum FaultDirection {
    Both,
    /// Bytes the gateway sends to the device.
    ToDevice,
    /// Bytes the device sends to the gateway.
    FromDevice,
}

/// The device and line options, common to `sim` and `demo`.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct DeviceArgs {
    /// The simulated device.
    #[arg(long, value_enum, default_value_t = ProfileName::CieM10)]
    pub(crate) profile: ProfileName,

    /// cie-m10: the unit id it answers.
    #[arg(long, default_value_t = 1, help_heading = "cie-m10 profile")]
    pub(crate) unit: u8,
    /// cie-m10: register of the 8 input ports.
    #[arg(
        long,
        default_value_t = 0,
        value_name = "REGISTER",
        help_heading = "cie-m10 profile"
    )]
    pub(crate) input_address: u16,
    /// cie-m10: register of the 8 output ports.
    #[arg(
        long,
        default_value_t = 8,
        value_name = "REGISTER",
        help_heading = "cie-m10 profile"
    )]
    pub(crate) output_address: u16,
    /// cie-m10: wire each output to its input, so inputs follow the outputs.
    #[arg(long, help_heading = "cie-m10 profile")]
    pub(crate) loopback: bool,
    /// Input port change notification, an unsolicited FC 03 response (transaction id
    /// 0) whenever an input changes (cie-m10), or on each scheduled change (generic:
    /// from the first unit, carrying the count of changes).
    #[arg(long, help_heading = "cie-m10 profile")]
    pub(crate) notify: bool,
    /// Change the inputs on a schedule: they count up by one every MS (cie-m10); the
    /// generic profile counts the changes.
    #[arg(long, value_name = "MS", help_heading = "cie-m10 profile")]
    pub(crate) toggle_ms: Option<u64>,

    /// generic: unit ids of the devices, comma separated.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1",
        value_name = "UNITS",
        help_heading = "generic profile"
    )]
    pub(crate) units: Vec<u8>,
    /// generic: holding registers start at zero, or each at its own address (so a
    /// reader can check every value it gets).
    #[arg(long, value_enum, default_value_t = Fill::Zero, help_heading = "generic profile")]
    pub(crate) fill: Fill,
    /// generic: coils and discrete inputs per device (at least 10).
    #[arg(long, default_value_t = generic::MIN_SIZE, value_name = "N", help_heading = "generic profile")]
    pub(crate) coils: usize,
    /// generic: holding and input registers per device (at least 10).
    #[arg(long, default_value_t = generic::MIN_SIZE, value_name = "N", help_heading = "generic profile")]
    pub(crate) registers: usize,

    /// Wait this long before answering each request.
    #[arg(
        long,
        default_value_t = 0,
        value_name = "MS",
        help_heading = "line model"
    )]
    pub(crate) delay_ms: u64,
    /// Lose each byte with this probability (0..1).
    #[arg(
        long,
        default_value_t = 0.0,
        value_name = "P",
        help_heading = "line model"
    )]
    pub(crate) drop: f64,
    /// Insert a burst of 1 to 8 random bytes before each byte with this probability
    /// (0..1).
    #[arg(
        long,
        default_value_t = 0.0,
        value_name = "P",
        help_heading = "line model"
    )]
    pub(crate) noise: f64,
    /// Replace each byte by another with this probability (0..1): a bit error, which
    /// MBAP has no checksum to catch.
    #[arg(
        long,
        default_value_t = 0.0,
        value_name = "P",
        help_heading = "line model"
    )]
    pub(crate) corrupt: f64,
    /// Which direction --drop, --noise and --corrupt hit.
    #[arg(long, value_enum, default_value_t = FaultDirection::Both, help_heading = "line model")]
    pub(crate) faults: FaultDirection,
    /// Seed of the line faults and of random inputs: the same seed loses the same bytes.
    /// Without it, one is chosen and logged.
    #[arg(long, help_heading = "line model")]
    pub(crate) seed: Option<u64>,
    /// Answer requests that arrive back to back (pipelined) in turn; without it, a
    /// request that arrives while the device is busy is ignored, as on the real device.
    #[arg(long, help_heading = "line model")]
    pub(crate) pipeline: bool,
    /// Hold each request until the bytes after it start another, or the line goes
    /// quiet, so a request that lost a byte is never executed with the next one's
    /// first byte. Costs up to --frame-gap-ms whenever the gateway pauses its pipeline.
    #[arg(long, help_heading = "line model")]
    pub(crate) confirm_requests: bool,
    /// Hand each frame to the line whole, one byte at a time, or in random bursts of
    /// 1 to 8 bytes, with --chunk-gap-ms between the pieces.
    #[arg(long, value_enum, default_value_t = ChunkMode::Whole, help_heading = "line model")]
    pub(crate) chunks: ChunkMode,
    /// The gap between pieces: exactly this one byte at a time, between half of it and
    /// all of it in random bursts.
    #[arg(
        long,
        default_value_t = 0,
        value_name = "MS",
        help_heading = "line model"
    )]
    pub(crate) chunk_gap_ms: u64,
    /// A partial request is discarded after this much silence.
    #[arg(
        long,
        default_value_t = 50,
        value_name = "MS",
        help_heading = "line model"
    )]
    pub(crate) frame_gap_ms: u64,

    /// Log level (RUST_LOG overrides). Each packet is logged at info.
    #[arg(long, value_name = "LEVEL")]
    pub(crate) log_level: Option<String>,
    /// No console even when stdin is a terminal.
    #[arg(long)]
    pub(crate) headless: bool,
}

/// Simulator or demo flags that cannot be used: a value out of range, or flags that
/// do not go together. The message names the flag; `mbgate` exits 2 on it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub(crate) struct BadFlags(String);

impl From<String> for BadFlags {
    fn from(said: String) -> Self {
        Self(said)
    }
}

impl From<&str> for BadFlags {
    fn from(said: &str) -> Self {
        Self(said.to_owned())
    }
}

/// `mbgate sim`'s settings: the device's (`device`), carrying frames as `framing`
/// asks (MBAP unless told), or a recorded device (`replay`), and paced at `pace` bits
/// a second when given. `framing` fits the profile: see [`framing_fits`].
pub(crate) fn settings(
    device: &DeviceArgs,
    replay: &ReplayArgs,
    framing: Option<Framing>,
    pace: Option<u32>,
) -> Result<Settings, BadFlags> {
    let mut s = device.settings()?;
    s.framing = framing.unwrap_or(Framing::Mbap);
    if !replay.replay.is_empty() {
        let r = super::replay::load(&replay.replay, replay.choices(), s.seed)
            .map_err(|e| e.to_string())?;
        s.framing = framing.or(r.framing()).unwrap_or(Framing::Mbap);
        s.device = Device::new(Profile::Replay(Box::new(r)), s.seed);
    }
    s.baud = pace;
    Ok(s)
}

/// Whether frames may be carried as `framing` for this device: RTU and ASCII need
/// the generic profile or a recorded device.
pub(crate) fn framing_fits(
    device: &DeviceArgs,
    replay: &ReplayArgs,
    framing: Option<Framing>,
) -> Result<(), BadFlags> {
    let framing = framing.unwrap_or(Framing::Mbap);
    if framing != Framing::Mbap && device.profile == ProfileName::CieM10 && replay.replay.is_empty()
    {
        return Err(
            "--framing rtu and ascii need --profile generic (the CIE-M10's serial \
             Modbus/TCP mode carries MBAP frames)"
                .into(),
        );
    }
    Ok(())
}

/// Validated simulator settings.
#[derive(Debug)]
pub(crate) struct Settings {
    /// The device, built from the profile flags.
    pub(crate) device: Device,
    /// How frames are carried: MBAP unless `mbgate sim --framing` says otherwise.
    pub(crate) framing: Framing,
    pub(crate) baud: Option<u32>,
    /// The bits of a character at that pace: start, data, parity, stop (the port's
    /// format; 10 for 8N1).
    pub(crate) char_bits: u32,
    pub(crate) delay: Duration,
    pub(crate) rx_faults: Faults,
    pub(crate) tx_faults: Faults,
    pub(crate) seed: u64,
    pub(crate) pipeline: bool,
    pub(crate) confirm_requests: bool,
    pub(crate) frame_gap: Duration,
    pub(crate) toggle: Option<Duration>,
    pub(crate) chunker: Chunker,
    /// What the simulator's own port adds to every reply's time, where it was measured
    /// (`--pty`: the pty's round trip). A replayed device's time already holds the path
    /// it was recorded through, so this much is taken off it.
    pub(crate) medium: Duration,
}

impl Settings {
    /// How frames are carried: as asked, else as recorded (`--replay`), else MBAP.
    pub(crate) fn framing(&self) -> Framing {
        self.framing
    }
}

/// Options that belong to the other profile are refused rather than ignored.
fn only_for(profile: &str, set: &[(&str, bool)]) -> Result<(), BadFlags> {
    match set.iter().find(|(_, given)| *given) {
        Some((flag, _)) => Err(format!("{flag} applies to the {profile} profile only").into()),
        None => Ok(()),
    }
}

impl DeviceArgs {
    pub(crate) fn settings(&self) -> Result<Settings, BadFlags> {
        for (flag, p) in [
            ("--drop", self.drop),
            ("--noise", self.noise),
            ("--corrupt", self.corrupt),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(format!("{flag} is a probability, 0 to 1; not {p}").into());
            }
        }
        if self.frame_gap_ms == 0 {
            return Err("--frame-gap-ms must be positive".into());
        }
        if self.toggle_ms == Some(0) {
            return Err("--toggle-ms must be positive".into());
        }
        let seed = self.seed.unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(1, |d| d.as_nanos() as u64)
        });
        let device = match self.profile {
            ProfileName::CieM10 => self.cie_m10_device(seed)?,
            ProfileName::Generic => self.generic_device(seed)?,
        };
        let faulty = |hit: bool, salt: u64| {
            if hit {
                Faults::new(self.drop, self.noise, seed ^ salt).with_corrupt(self.corrupt)
            } else {
                Faults::none()
            }
        };
        Ok(Settings {
            device,
            framing: Framing::Mbap,
            baud: None,
            char_bits: 10,
            delay: Duration::from_millis(self.delay_ms),
            rx_faults: faulty(self.faults != FaultDirection::FromDevice, 0),
            tx_faults: faulty(
                self.faults != FaultDirection::ToDevice,
                0x9E37_79B9_7F4A_7C15,
            ),
            seed,
            pipeline: self.pipeline,
            confirm_requests: self.confirm_requests,
            frame_gap: Duration::from_millis(self.frame_gap_ms),
            toggle: self.toggle_ms.map(Duration::from_millis),
            chunker: Chunker::new(
                self.chunks,
                Duration::from_millis(self.chunk_gap_ms),
                seed ^ 0x5EED,
            ),
            medium: Duration::ZERO,
        })
    }

    /// The CIE-M10 profile's device; the generic profile's flags refused.
    fn cie_m10_device(&self, seed: u64) -> Result<Device, BadFlags> {
        only_for(
            "generic",
            &[
                ("--units", self.units != [1]),
                ("--coils", self.coils != generic::MIN_SIZE),
                ("--registers", self.registers != generic::MIN_SIZE),
                ("--fill", self.fill != Fill::Zero),
            ],
        )?;
        if self.input_address == self.output_address {
            return Err(format!(
                "--input-address and --output-address are both {}",
                self.input_address
            )
            .into());
        }
        Ok(Device::new(
            Profile::CieM10(CieM10 {
                unit: self.unit,
                input_address: self.input_address,
                output_address: self.output_address,
                loopback: self.loopback,
                notify: self.notify,
                ..CieM10::default()
            }),
            seed,
        ))
    }

    /// The generic profile's device; the CIE-M10 profile's flags refused.
    fn generic_device(&self, seed: u64) -> Result<Device, BadFlags> {
        only_for(
            "cie-m10",
            &[
                ("--unit", self.unit != 1),
                ("--input-address", self.input_address != 0),
                ("--output-address", self.output_address != 8),
                ("--loopback", self.loopback),
            ],
        )?;
        if let Some(u) = self.units.iter().find(|u| !(1..=247).contains(*u)) {
            return Err(format!("--units: unit ids are 1..247, not {u}").into());
        }
        for (flag, n) in [("--coils", self.coils), ("--registers", self.registers)] {
            if !(generic::MIN_SIZE..=generic::MAX_SIZE).contains(&n) {
                return Err(format!(
                    "{flag} must be {}..{}, not {n}",
                    generic::MIN_SIZE,
                    generic::MAX_SIZE
                )
                .into());
            }
        }
        let mut d = Device::generic(
            &self.units,
            self.coils,
            self.registers,
            seed.wrapping_add(2),
        );
        match self.fill {
            Fill::Zero => {}
            Fill::Address => d.fill_holding_with_addresses(),
            Fill::Header => d.fill_holding(generic::header_fill),
        }
        if self.notify {
            d.notify_generic();
        }
        Ok(d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct T {
        #[command(flatten)]
        d: DeviceArgs,
    }

    fn settings(args: &[&str]) -> Result<Settings, BadFlags> {
        T::try_parse_from(std::iter::once("t").chain(args.iter().copied()))
            .map_err(|e| BadFlags::from(e.to_string()))?
            .d
            .settings()
    }

    #[test]
    fn refuses_what_does_not_apply() {
        assert_eq!(
            settings(&["--units", "1,2"]).unwrap_err().to_string(),
            "--units applies to the generic profile only"
        );
        assert_eq!(
            settings(&["--profile", "generic", "--loopback"])
                .unwrap_err()
                .to_string(),
            "--loopback applies to the cie-m10 profile only"
        );
        assert_eq!(
            settings(&["--drop", "1.5"]).unwrap_err().to_string(),
            "--drop is a probability, 0 to 1; not 1.5"
        );
        assert_eq!(
            settings(&["--profile", "generic", "--coils", "9"])
                .unwrap_err()
                .to_string(),
            "--coils must be 10..65536, not 9"
        );
        assert_eq!(
            settings(&["--output-address", "0"])
                .unwrap_err()
                .to_string(),
            "--input-address and --output-address are both 0"
        );
        assert!(settings(&[
            "--profile",
            "generic",
            "--units",
            "1,2,247",
            "--registers",
            "100"
        ])
        .is_ok());
    }

    #[test]
    fn faults_hit_the_chosen_direction() {
        let s = settings(&["--drop", "0.1", "--faults", "from-device", "--seed", "5"]).unwrap();
        assert!(!s.rx_faults.is_active() && s.tx_faults.is_active());
        assert_eq!(s.seed, 5);
        let s = settings(&["--noise", "0.1", "--faults", "to-device"]).unwrap();
        assert!(s.rx_faults.is_active() && !s.tx_faults.is_active());
    }
}
