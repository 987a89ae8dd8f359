//! `mbgate scan` on a serial port: each setting opened in turn (exclusively: a port a
//! gateway holds is refused, naming the process), each unit asked with the
//! 3.5-character gap before it, kept with the line's microsecond timer, and a reply
//! awaited for its time on the wire plus the timeout.

use super::probe::{self, AtSetting, Heard, ProbeSetting, SerialFraming};
use super::{Found, Progress, Report, ScanError, SerialSetting};
use crate::config::{FlowControl, Parity as CfgParity, SerialConfig};
use crate::line::port::serial::PreciseTimer;
use crate::tools::wire::uart::Parity;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::time::Instant;
use tokio_serial::{ClearBuffer, SerialPort, SerialStream};
use tokio_util::sync::CancellationToken;

/// How long the line is listened to after the last unit of a wide setting, for a
/// slow unit's late reply (docs/scan.md).
const LINGER: Duration = Duration::from_millis(500);

/// The longest reply awaited to an identity request (a PDU of 253 bytes).
const LONGEST_PDU: usize = 253;

/// One open port at one setting, and the time of the last byte on its line.
struct OpenSetting<'a> {
    port: SerialStream,
    timer: &'a mut PreciseTimer,
    setting: &'a ProbeSetting,
    /// When the line last carried a byte: the gap before a request counts from it.
    last: Instant,
    timeout: Duration,
    /// How long after the request had left the last frame that answered came (none
    /// when it was a late reply to an earlier request).
    replied: Option<Duration>,
}

/// A character's time at setting `s`.
fn char_time_at(s: &ProbeSetting) -> Duration {
    Duration::from_nanos((u64::from(s.format.bits()) * 1_000_000_000).div_ceil(u64::from(s.baud)))
}

impl OpenSetting<'_> {
    /// A character's time on this line.
    fn char_time(&self) -> Duration {
        char_time_at(self.setting)
    }

    /// The longest a try at `framing` waits for a read's reply, the request's time
    /// included: the budget of the time left.
    fn read_cost(&self, framing: SerialFraming) -> Duration {
        OpenSetting::cost(self.setting, framing, self.timeout)
    }

    /// Sends `pdu` to `unit` after the 3.5-character gap, and returns what came back:
    /// as soon as a frame with a good check answers it, else after the request's and
    /// the longest reply's time on the wire plus the timeout.
    async fn ask(
        &mut self,
        framing: SerialFraming,
        unit: u8,
        pdu: &[u8],
    ) -> Result<Heard, ScanError> {
        let gap = Duration::from_micros(crate::frame::rtu::t35_us(
            self.setting.baud,
            self.setting.format.bits(),
        ));
        self.timer.until(self.last + gap).await?;
        // What came since the last window is not this request's reply, but may be a
        // slow unit's late one to an earlier request: kept aside, and judged alone
        // when this request gets no reply of its own.
        let mut early = Vec::new();
        let waiting = self.port.bytes_to_read().unwrap_or(0) as usize;
        if waiting > 0 {
            let mut buf = vec![0u8; waiting.min(4096)];
            let n = self.port.read(&mut buf).await?;
            early.extend_from_slice(&buf[..n]);
        }
        let _ = self.port.clear(ClearBuffer::Input);
        let request = framing.codec().encode(unit, pdu);
        self.port.write_all(&request).await?;
        let written = Instant::now();
        let on_wire = self.char_time() * request.len() as u32;
        let reply_pdu = if pdu[0] == 3 || pdu[0] == 4 {
            4
        } else {
            LONGEST_PDU
        };
        let deadline = written
            + on_wire
            + self.char_time() * framing.codec().encoded_len(reply_pdu) as u32
            + self.timeout;
        self.last = written + on_wire;
        let (heard, first_byte) = self.hear(framing, &request, pdu[0], deadline).await?;
        if matches!(heard, Heard::Frame { .. }) {
            self.replied = Some(
                first_byte
                    .unwrap_or_else(Instant::now)
                    .saturating_duration_since(written + on_wire),
            );
            return Ok(heard);
        }
        if let late @ Heard::Frame { .. } = probe::judge(framing, &[], pdu[0], &early) {
            self.replied = None;
            return Ok(late);
        }
        Ok(heard)
    }

    /// Reads until a frame with a good check answers `function` (after `request`'s
    /// echo, if the line echoes), or until `deadline`: what was heard, and when the
    /// first byte past the echo came.
    async fn hear(
        &mut self,
        framing: SerialFraming,
        request: &[u8],
        function: u8,
        deadline: Instant,
    ) -> Result<(Heard, Option<Instant>), ScanError> {
        let mut got = Vec::new();
        let mut chunk = [0u8; 512];
        let mut first_byte = None;
        loop {
            tokio::select! {
                r = self.port.read(&mut chunk) => {
                    let n = r?;
                    if n == 0 {
                        break;
                    }
                    got.extend_from_slice(&chunk[..n]);
                    let echo = request.len().min(got.len());
                    if first_byte.is_none()
                        && (got[..echo] != request[..echo] || got.len() > request.len())
                    {
                        first_byte = Some(Instant::now());
                    }
                    self.last = self.last.max(Instant::now());
                    let heard = probe::judge(framing, request, function, &got);
                    if matches!(heard, Heard::Frame { .. }) {
                        return Ok((heard, first_byte));
                    }
                }
                r = self.timer.until(deadline) => {
                    r?;
                    break;
                }
            }
        }
        Ok((probe::judge(framing, request, function, &got), first_byte))
    }

    /// Reads for `how_long` without asking, and judges what came as a late reply
    /// to a read.
    async fn linger(
        &mut self,
        framing: SerialFraming,
        how_long: Duration,
    ) -> Result<Heard, ScanError> {
        let deadline = Instant::now() + how_long;
        Ok(self.hear(framing, &[], 3, deadline).await?.0)
    }

    /// Brings a device's receiver back to idle before the first request at a
    /// setting, whatever garbage the tries at other settings left in it
    /// (docs/scan.md): RTU, a silence of 3.5 characters (from now: the open has
    /// just cleared what was queued), which ends any frame; ASCII, CR LF, which ends
    /// whatever a ':' of garbage began, so the device drops it as a bad frame and
    /// hears the next ':' afresh.
    async fn clear_receiver(&mut self, framing: SerialFraming) -> Result<(), ScanError> {
        if framing == SerialFraming::Ascii {
            self.port.write_all(b"\r\n").await?;
            self.last = Instant::now() + self.char_time() * 2;
        } else {
            self.last = self.last.max(Instant::now());
        }
        Ok(())
    }
}

/// The port's configuration at `s`: no flow control (a scan needs none, and a bus
/// adapter wires none).
pub(super) fn config(path: &str, s: &ProbeSetting) -> SerialConfig {
    SerialConfig {
        path: path.to_string(),
        baud_rate: s.baud,
        data_bits: s.format.data_bits,
        parity: match s.format.parity {
            Parity::None => CfgParity::None,
            Parity::Even => CfgParity::Even,
            Parity::Odd => CfgParity::Odd,
        },
        stop_bits: s.format.stop_bits,
        flow_control: FlowControl::None,
        ..SerialConfig::default()
    }
}

/// Scans `path` at each of `settings` in turn; see docs/scan.md for the rules.
#[allow(clippy::too_many_arguments)]
pub(super) async fn scan(
    path: &str,
    settings: &[ProbeSetting],
    units: &[u8],
    give_up: usize,
    wide: &[SerialSetting],
    timeout: Duration,
    all: bool,
    stop: &CancellationToken,
    progress: &mut Progress,
) -> Result<Report, ScanError> {
    let plan = ScanPlan {
        settings,
        units,
        give_up,
        wide,
        timeout,
        stop,
    };
    let mut tally = ScanTally {
        report: Report::default(),
        done: 0,
        total: plan.total(),
        progress,
    };
    let mut timer = PreciseTimer::new()?;
    'settings: for (i, s) in settings.iter().enumerate() {
        if stop.is_cancelled() {
            break;
        }
        let port = crate::line::port::serial::open(&config(path, s)).map_err(|source| {
            ScanError::Open {
                path: path.to_string(),
                source,
            }
        })?;
        let mut line = OpenSetting {
            port,
            timer: &mut timer,
            setting: s,
            last: Instant::now(),
            timeout,
            replied: None,
        };
        for (k, &framing) in s.framings.iter().enumerate() {
            let (at, mut found_here) = plan.framing(&mut line, i, k, framing, &mut tally).await?;
            let report = &mut tally.report;
            line.identify(framing, &mut found_here, &mut report.tries, stop)
                .await?;
            // In the order of their ids, late replies included.
            found_here.sort_by_key(|f| f.unit);
            report.found.extend(found_here);
            if stop.is_cancelled() || (at.proven && !all) {
                break 'settings;
            }
        }
    }
    Ok(tally.report)
}

/// What a serial scan tries: the settings, the units, and how far at each.
struct ScanPlan<'a> {
    settings: &'a [ProbeSetting],
    units: &'a [u8],
    give_up: usize,
    wide: &'a [SerialSetting],
    timeout: Duration,
    stop: &'a CancellationToken,
}

/// How far a serial scan is: what it found and its tries, done of the total.
struct ScanTally<'p> {
    report: Report,
    done: usize,
    total: usize,
    progress: &'p mut Progress,
}

impl ScanPlan<'_> {
    /// Every unit at a wide setting; the first `give_up` elsewhere, until proven.
    fn limit(&self, s: &ProbeSetting, f: SerialFraming) -> usize {
        if self.wide.contains(&(s.baud, s.format, f)) {
            self.units.len()
        } else {
            self.give_up.min(self.units.len())
        }
    }

    /// The tries planned, before any setting is proven.
    fn total(&self) -> usize {
        self.settings
            .iter()
            .flat_map(|s| s.framings.iter().map(move |&f| self.limit(s, f)))
            .sum()
    }

    /// The time the tries after setting `i`'s framing `k` take: the rest of that
    /// setting's, then every later one's.
    fn later(&self, i: usize, k: usize) -> Duration {
        self.settings[i..]
            .iter()
            .enumerate()
            .flat_map(|(j, t)| {
                let skip = if j == 0 { k + 1 } else { 0 };
                t.framings.iter().skip(skip).map(move |&f| (t, f))
            })
            .map(|(t, f)| OpenSetting::cost(t, f, self.timeout) * self.limit(t, f) as u32)
            .sum()
    }

    /// Asks the units at setting `i` in its framing `k`, on `line`: how the setting
    /// fared, and the units found there (identities not asked yet).
    async fn framing(
        &self,
        line: &mut OpenSetting<'_>,
        i: usize,
        k: usize,
        framing: SerialFraming,
        tally: &mut ScanTally<'_>,
    ) -> Result<(AtSetting, Vec<Found>), ScanError> {
        let (s, units, stop) = (&self.settings[i], self.units, self.stop);
        let per_setting = self.limit(s, framing);
        let mut at = AtSetting::new(units.to_vec(), per_setting);
        line.clear_receiver(framing).await?;
        let mut found_here = Vec::new();
        'units: loop {
            self.ask_units(line, i, k, framing, &mut at, &mut found_here, tally)
                .await?;
            if stop.is_cancelled() || at.proven || per_setting < units.len() {
                break;
            }
            // The last units of a wide setting have no later window for a slow
            // reply to come in: the line is listened to a while before it is left.
            if let Heard::Frame { unit: from, pdu } = line.linger(framing, LINGER).await? {
                if units.contains(&from) {
                    at.proven = true;
                    let after = tally.progress.started.elapsed();
                    found_here.push(heard_at(from, s, framing, &pdu, None, after));
                    continue 'units;
                }
            }
            break;
        }
        if let (Some(first), false) = (at.unanswering, at.proven) {
            tally
                .report
                .unanswering
                .push(((s.baud, s.format, framing), first));
        } else if at.garbage && !at.proven {
            tally.report.garbage.push((s.baud, s.format, framing));
        }
        Ok((at, found_here))
    }

    /// Asks each unit `at` has left at setting `i`'s framing `k` (until `stop`),
    /// keeping in `found_here` the units that answered, late replies included.
    #[allow(clippy::too_many_arguments)]
    async fn ask_units(
        &self,
        line: &mut OpenSetting<'_>,
        i: usize,
        k: usize,
        framing: SerialFraming,
        at: &mut AtSetting,
        found_here: &mut Vec<Found>,
        tally: &mut ScanTally<'_>,
    ) -> Result<(), ScanError> {
        let (s, units, stop) = (&self.settings[i], self.units, self.stop);
        let per_setting = self.limit(s, framing);
        let what = format!("{} {} {}", s.baud, s.format, framing.name());
        while let Some(unit) = at.next_unit() {
            if stop.is_cancelled() {
                // What was found so far is kept (and reported) by the caller.
                break;
            }
            // The time left: this setting's tries, then every later one's.
            let left = line.read_cost(framing) * at.left() as u32 + self.later(i, k);
            let progress = &mut tally.progress;
            progress.show(
                tally.done,
                tally.total,
                left,
                &format!("{what} unit {unit}"),
            );
            let mut heard = line.ask(framing, unit, &probe::read_one(3)).await?;
            tally.report.tries += 1;
            if heard == Heard::Nothing && at.proven {
                // No answer at all to FC 03 where a device is known to be: some
                // devices keep silent for a function they lack; FC 04 too.
                heard = line.ask(framing, unit, &probe::read_one(4)).await?;
                tally.report.tries += 1;
            }
            let replied = line.replied;
            let was_proven = at.proven;
            at.record(&heard);
            tally.done += 1;
            if at.proven && !was_proven {
                tally.total += units.len().saturating_sub(per_setting);
            }
            if let Heard::Frame { unit: from, pdu } = &heard {
                // A frame from a unit asked before is its late reply: each unit is
                // asked once, so it can be no other's.
                let late = *from != unit
                    && units.contains(from)
                    && !found_here.iter().any(|f: &Found| f.unit == *from);
                if *from == unit || late {
                    // A late reply's time is not known: it answered a request
                    // before this one.
                    let replied = if late { None } else { replied };
                    let after = tally.progress.started.elapsed();
                    found_here.push(heard_at(*from, s, framing, pdu, replied, after));
                }
            }
        }
        Ok(())
    }
}

/// A unit heard at setting `s` in `framing`, its identities not asked yet.
fn heard_at(
    unit: u8,
    s: &ProbeSetting,
    framing: SerialFraming,
    pdu: &[u8],
    replied: Option<Duration>,
    after: Duration,
) -> Found {
    Found {
        unit,
        serial: Some((s.baud, s.format, framing)),
        answered: probe::describe(pdu),
        device_id: Err(probe::NoIdentity::NotAsked),
        server_id: Err(probe::NoIdentity::NotAsked),
        replies: replied.into_iter().collect(),
        after,
    }
}

impl OpenSetting<'_> {
    /// Asks `pdu` of `unit` as [`OpenSetting::ask`] does, once more when nothing came:
    /// a device busy with something else may miss one request.
    async fn ask_twice(
        &mut self,
        framing: SerialFraming,
        unit: u8,
        pdu: &[u8],
        tries: &mut usize,
    ) -> Result<Heard, ScanError> {
        let mut heard = self.ask(framing, unit, pdu).await?;
        *tries += 1;
        if heard == Heard::Nothing {
            heard = self.ask(framing, unit, pdu).await?;
            *tries += 1;
        }
        Ok(heard)
    }

    /// The units found at this setting: their identities and a few timed reads. A
    /// unit found is known to be there, so these get the gateway's own default
    /// timeout: a slow unit's reply times are had, not only the fast pass's window.
    async fn identify(
        &mut self,
        framing: SerialFraming,
        found: &mut [Found],
        tries: &mut usize,
        stop: &CancellationToken,
    ) -> Result<(), ScanError> {
        let window = self.timeout;
        self.timeout = window.max(Duration::from_millis(
            crate::config::RelayConfig::default().response_timeout_ms,
        ));
        for f in found.iter_mut() {
            if stop.is_cancelled() {
                break;
            }
            let device = self
                .ask_twice(framing, f.unit, &probe::DEVICE_ID, tries)
                .await?;
            f.timed(&device, self.replied);
            let server = self
                .ask_twice(framing, f.unit, &probe::SERVER_ID, tries)
                .await?;
            f.timed(&server, self.replied);
            // A few more reads, for a reply time worth a median.
            for _ in 0..super::TIMED_READS {
                let heard = self.ask(framing, f.unit, &probe::read_one(3)).await?;
                *tries += 1;
                f.timed(&heard, self.replied);
            }
            super::identified(f, &device, &server);
        }
        self.timeout = window;
        Ok(())
    }

    /// [`OpenSetting::read_cost`] at setting `s`, open or not yet.
    fn cost(s: &ProbeSetting, framing: SerialFraming, timeout: Duration) -> Duration {
        let chars = framing.codec().encoded_len(5) + framing.codec().encoded_len(4);
        char_time_at(s) * chars as u32 + timeout
    }
}
