//! The settings a unit of a line has of its own (docs/configuration.md "Per-unit
//! settings"): the `[[line.unit]]` tables read, checked and printed here, and each
//! unit's effective settings, the line's where a table says nothing.
//!
//! ```toml
//! [[line.unit]]
//! units = "1-5"                 # a unit id, a range, or a list of both
//! response_timeout_ms = 100
//!
//! [[line.unit]]
//! units = [7]
//! response_timeout_ms = "auto"  # learned from the unit's replies
//! response_timeout_max_ms = 1000
//! ```

use super::raw::{read_table, Raw};
use super::{table, Check, Key, RelayConfig, Setting, ValueError, ValueKind};
use super::{Any, Range, PAUSE_MS, RETRIES, TIMEOUT_MS};
use std::collections::BTreeSet;
use std::time::Duration;

impl RelayConfig {
    /// The longest the relay takes to answer a request that is on the line: the
    /// response timeout of every attempt (docs/design.md §1 step 5).
    pub fn answer_within(&self) -> Duration {
        Duration::from_millis(self.response_timeout_ms * u64::from(self.retries + 1))
    }
}

table! {
    /// One `[[line.unit]]` as the file gives it (docs/configuration.md "Per-unit
    /// settings"); each key left out is the line's.
    ["line.unit"] UnitTableKeys UNIT_KEYS {
        /// A unit id, a range "A-B", or a list of both, 1 to 255; required
        units: UnitIds = UnitIds::default(), Range(1, 255, None);
        /// This unit's response timeout; or "auto": learned from its replies
        response_timeout_ms: UnitTimeout = UnitTimeout::Auto, TIMEOUT_MS;
        /// With "auto": the ceiling, where the learning starts (the line's response_timeout_ms when left out)
        response_timeout_max_ms: u64 = 0, TIMEOUT_MS;
        /// With "auto": the floor
        response_timeout_min_ms: u64 = LEARNED_FLOOR_MS, TIMEOUT_MS;
        /// Quiet time after a transaction with this unit before the next request
        request_pause_ms: u64 = 0, PAUSE_MS;
        /// Resends after a timeout or a bad reply
        retries: u32 = 0, RETRIES;
        /// Resend this unit's writes too
        retry_writes: bool = false, Any;
    }
}

/// A learned timeout never goes below this unless `response_timeout_min_ms` says
/// otherwise: near it a USB adapter's latency timer (1 to 16 ms), the kernel's and
/// the relay's own scheduling on a busy machine make up much of what is measured, and
/// a stall of the machine would time a healthy unit out.
pub(crate) const LEARNED_FLOOR_MS: u64 = 50;

/// A unit's response timeout: a number of milliseconds, or learned from its replies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UnitTimeout {
    Ms(u64),
    /// `"auto"`: learned (docs/reliability.md "Learned timeouts").
    Auto,
}

impl Setting for UnitTimeout {
    const KIND: ValueKind = ValueKind::Str;
    fn read(raw: &Raw, check: &Check) -> Result<Self, ValueError> {
        match raw {
            Raw::Str(w) if w.trim() == "auto" => Ok(UnitTimeout::Auto),
            Raw::Str(w) => Err(format!(
                "invalid value {w:?}; expected \"auto\" or a number of milliseconds"
            )
            .into()),
            _ => u64::read(raw, check).map(UnitTimeout::Ms),
        }
    }
    fn print(&self) -> String {
        match self {
            UnitTimeout::Ms(ms) => ms.to_string(),
            UnitTimeout::Auto => "\"auto\"".into(),
        }
    }
}

/// `units = 3`, `"1-5"` or `[1, "10-20"]`: unit ids as `check` bounds them, none twice.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct UnitIds(pub(crate) BTreeSet<u8>);

impl Setting for UnitIds {
    const KIND: ValueKind = ValueKind::List;
    fn read(raw: &Raw, check: &Check) -> Result<Self, ValueError> {
        let one = |v: &Raw| -> Result<(u8, u8), ValueError> {
            match v {
                Raw::Str(s) => range(s),
                other => u8::read(other, check).map(|u| (u, u)),
            }
        };
        let parts = match raw {
            Raw::List(a) if a.is_empty() => return Err("must list at least one unit id".into()),
            Raw::List(a) => a
                .iter()
                .enumerate()
                .map(|(i, v)| one(v).map_err(|e| e.item(i)))
                .collect::<Result<_, _>>()?,
            other => vec![one(other)?],
        };
        let mut ids = BTreeSet::new();
        for (first, last) in parts {
            for u in first..=last {
                if !ids.insert(u) {
                    return Err(format!("unit {u} is listed twice").into());
                }
            }
        }
        Ok(Self(ids))
    }
    fn print(&self) -> String {
        let ids: Vec<u8> = self.0.iter().copied().collect();
        crate::access::rules::id_list(&ids)
    }
}

/// What one `[[line.unit]]` table says; `None`: the line's.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub(crate) struct UnitSettings {
    pub(crate) response_timeout: Option<UnitTimeout>,
    /// With `"auto"`: the ceiling, where the learning starts (the line's
    /// `response_timeout_ms` when not given).
    pub(crate) response_timeout_max_ms: Option<u64>,
    /// With `"auto"`: the floor ([`LEARNED_FLOOR_MS`] when not given).
    pub(crate) response_timeout_min_ms: Option<u64>,
    pub(crate) request_pause_ms: Option<u64>,
    pub(crate) retries: Option<u32>,
    pub(crate) retry_writes: Option<bool>,
}

/// One `[[line.unit]]`: its unit ids (as the line knows them) and its settings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct UnitTable {
    pub(crate) ids: BTreeSet<u8>,
    pub(crate) settings: UnitSettings,
}

/// A line's `[[line.unit]]` tables, in the order of the file; no unit in two.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct UnitTables(pub(crate) Vec<UnitTable>);

/// A unit's response timeout as the relay applies it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Timeout {
    Fixed(Duration),
    /// Learned, within `[floor, ceiling]`, starting at the ceiling.
    Learned {
        floor: Duration,
        ceiling: Duration,
    },
}

/// A unit's effective settings: its table's, else the line's.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct UnitPolicy {
    pub(crate) timeout: Timeout,
    /// Quiet time after a transaction with this unit, before the next request.
    pub(crate) pause: Duration,
    pub(crate) retries: u32,
    pub(crate) retry_writes: bool,
}

impl UnitPolicy {
    /// The line's own settings, for a unit no table names.
    pub(crate) fn of_line(relay: &RelayConfig) -> Self {
        UnitSettings::default().resolve(relay)
    }

    /// In a few words, for `mbgate check-config` and the log.
    pub(crate) fn describe(&self) -> String {
        let ms = |d: Duration| d.as_millis();
        let timeout = match self.timeout {
            Timeout::Fixed(d) => format!("response timeout {} ms", ms(d)),
            Timeout::Learned { floor, ceiling } => format!(
                "response timeout learned between {} and {} ms",
                ms(floor),
                ms(ceiling)
            ),
        };
        let writes = if self.retry_writes {
            "writes resent too"
        } else {
            "writes not resent"
        };
        format!(
            "{timeout}, pause {} ms, {} retries, {writes}",
            ms(self.pause),
            self.retries
        )
    }
}

impl UnitSettings {
    /// These settings over the line's.
    pub(crate) fn resolve(&self, relay: &RelayConfig) -> UnitPolicy {
        let ms = Duration::from_millis;
        let line = relay.response_timeout_ms;
        let timeout = match self.response_timeout {
            None => Timeout::Fixed(ms(line)),
            Some(UnitTimeout::Ms(t)) => Timeout::Fixed(ms(t)),
            Some(UnitTimeout::Auto) => {
                let ceiling = self.response_timeout_max_ms.unwrap_or(line);
                let floor = self.response_timeout_min_ms.unwrap_or(LEARNED_FLOOR_MS);
                Timeout::Learned {
                    floor: ms(floor.min(ceiling)),
                    ceiling: ms(ceiling),
                }
            }
        };
        UnitPolicy {
            timeout,
            pause: ms(self.request_pause_ms.unwrap_or(relay.request_pause_ms)),
            retries: self.retries.unwrap_or(relay.retries),
            retry_writes: self.retry_writes.unwrap_or(relay.retry_writes),
        }
    }
}

impl UnitTables {
    pub(crate) fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The table that names `unit`, if one does.
    pub(crate) fn settings(&self, unit: u8) -> Option<&UnitSettings> {
        self.0
            .iter()
            .find(|t| t.ids.contains(&unit))
            .map(|t| &t.settings)
    }

    /// `unit`'s effective settings on a line of `relay`.
    pub(crate) fn policy(&self, relay: &RelayConfig, unit: u8) -> UnitPolicy {
        match self.settings(unit) {
            Some(s) => s.resolve(relay),
            None => UnitPolicy::of_line(relay),
        }
    }

    /// Each named unit with its effective settings, a line each (`mbgate
    /// check-config`): `unit 1: response timeout 100 ms, ...`; then the others.
    pub(crate) fn describe(&self, relay: &RelayConfig) -> Vec<String> {
        let mut out = Vec::new();
        for t in &self.0 {
            for &u in &t.ids {
                out.push(format!(
                    "unit {u}: {}",
                    t.settings.resolve(relay).describe()
                ));
            }
        }
        if !out.is_empty() {
            let line = UnitPolicy::of_line(relay).describe();
            out.push(format!("other units: {line}"));
        }
        out
    }

    /// The longest the line takes to answer a request it holds: the longest timeout
    /// (a learned one's ceiling) of any unit, times its attempts.
    pub(crate) fn answer_within(&self, relay: &RelayConfig) -> Duration {
        let each = self.0.iter().map(|t| {
            let p = t.settings.resolve(relay);
            let longest = match p.timeout {
                Timeout::Fixed(d) => d,
                Timeout::Learned { ceiling, .. } => ceiling,
            };
            longest * (p.retries + 1)
        });
        each.fold(relay.answer_within(), Duration::max)
    }

    /// The `[[line.unit]]` tables as the `[[line]]` form prints them; `parse` reads
    /// them back to the same.
    pub(crate) fn to_toml(&self) -> String {
        let mut out = String::new();
        for t in &self.0 {
            let ids: Vec<u8> = t.ids.iter().copied().collect();
            out += &format!(
                "\n[[line.unit]]\nunits = {}\n",
                crate::access::rules::id_list(&ids)
            );
            let s = &t.settings;
            match s.response_timeout {
                Some(UnitTimeout::Ms(ms)) => out += &format!("response_timeout_ms = {ms}\n"),
                Some(UnitTimeout::Auto) => out += "response_timeout_ms = \"auto\"\n",
                None => {}
            }
            let mut num = |key: &str, v: Option<u64>| {
                if let Some(v) = v {
                    out += &format!("{key} = {v}\n");
                }
            };
            num("response_timeout_max_ms", s.response_timeout_max_ms);
            num("response_timeout_min_ms", s.response_timeout_min_ms);
            num("request_pause_ms", s.request_pause_ms);
            num("retries", s.retries.map(u64::from));
            if let Some(b) = s.retry_writes {
                out += &format!("retry_writes = {b}\n");
            }
        }
        out
    }
}

/// The `[[line.unit]]` array `raw`; `path` is what messages call it (`line[0].unit`).
pub(super) fn tables(raw: &Raw, path: &str) -> Result<UnitTables, ValueError> {
    // `unit = [1]` is most likely the line's `units` misspelt.
    let expected = "expected [[line.unit]] tables (the unit ids the line serves are its `units`)";
    let tables = match raw {
        Raw::List(tables) if tables.iter().all(|t| matches!(t, Raw::Table(_))) => tables,
        _ => return Err(expected.into()),
    };
    let mut out: Vec<UnitTable> = Vec::new();
    for (i, t) in tables.iter().enumerate() {
        let u = table(t, &format!("{path}[{i}]")).map_err(|e| e.item(i))?;
        for &id in &u.ids {
            if let Some(j) = out.iter().position(|o| o.ids.contains(&id)) {
                let m = format!("unit {id} is also in {path}[{j}]");
                return Err(ValueError::new(m).value("units").item(i));
            }
        }
        out.push(u);
    }
    Ok(UnitTables(out))
}

/// One `[[line.unit]]`, read by [`UNIT_KEYS`]; `path` is what messages call it.
fn table(raw: &Raw, path: &str) -> Result<UnitTable, ValueError> {
    let (t, given) = read_table(raw, UNIT_KEYS, "expected a table ([[line.unit]])")?;
    let has = |k: &str| given.contains(&k);
    let s = UnitSettings {
        response_timeout: has("response_timeout_ms").then_some(t.response_timeout_ms),
        response_timeout_max_ms: has("response_timeout_max_ms")
            .then_some(t.response_timeout_max_ms),
        response_timeout_min_ms: has("response_timeout_min_ms")
            .then_some(t.response_timeout_min_ms),
        request_pause_ms: has("request_pause_ms").then_some(t.request_pause_ms),
        retries: has("retries").then_some(t.retries),
        retry_writes: has("retry_writes").then_some(t.retry_writes),
    };
    if let (Some(min), Some(max)) = (s.response_timeout_min_ms, s.response_timeout_max_ms) {
        if min > max {
            let m = format!("must not be below {path}.response_timeout_min_ms ({min}), got {max}");
            return Err(ValueError::new(m).value("response_timeout_max_ms"));
        }
    }
    let learned_only = s.response_timeout_max_ms.is_some() || s.response_timeout_min_ms.is_some();
    if learned_only && s.response_timeout != Some(UnitTimeout::Auto) {
        let key = match s.response_timeout_max_ms {
            Some(_) => "response_timeout_max_ms",
            None => "response_timeout_min_ms",
        };
        let m = "bounds a learned timeout: give response_timeout_ms = \"auto\" with it";
        return Err(ValueError::new(m).value(key));
    }
    if !has("units") {
        let m = "missing: the unit ids these settings are for, e.g. units = \"1-5\"";
        return Err(ValueError::new(m).value("units"));
    }
    Ok(UnitTable {
        ids: t.units.0,
        settings: s,
    })
}

/// `"10-20"` (or `"7"`): the units 10 to 20.
fn range(s: &str) -> Result<(u8, u8), ValueError> {
    let bad = || format!("expected a unit id or a range like \"1-5\", got {s:?}");
    let unit = |x: &str| x.trim().parse::<u8>().ok().filter(|u| *u >= 1);
    let Some((a, b)) = s.split_once('-') else {
        return unit(s).map(|u| (u, u)).ok_or_else(|| bad().into());
    };
    match (unit(a), unit(b)) {
        (Some(a), Some(b)) if a <= b => Ok((a, b)),
        (Some(_), Some(_)) => Err(format!("the range {s:?} is empty").into()),
        _ => Err(bad().into()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::parse;

    fn line_with(units: &str) -> String {
        format!("[[line]]\nserial = {{ path = \"/dev/x\", framing = \"rtu\" }}\nrelay = {{ response_timeout_ms = 400, retries = 1 }}\n{units}")
    }

    #[test]
    fn a_unit_gets_its_tables_settings_and_the_line_the_rest() {
        let cfg = parse(
            &line_with(
                "[[line.unit]]\nunits = \"1-3\"\nresponse_timeout_ms = 100\nrequest_pause_ms = 5\n\
                 [[line.unit]]\nunits = [7, \"9-10\"]\nresponse_timeout_ms = \"auto\"\nresponse_timeout_max_ms = 900\nretry_writes = true\n",
            ),
            "t.toml",
        )
        .unwrap();
        let line = &cfg.lines[0];
        let ms = Duration::from_millis;
        let p = |u| line.unit_tables.policy(&line.relay, u);
        assert_eq!(p(2).timeout, Timeout::Fixed(ms(100)));
        assert_eq!(
            (p(2).pause, p(2).retries, p(2).retry_writes),
            (ms(5), 1, false)
        );
        assert_eq!(
            p(10).timeout,
            Timeout::Learned {
                floor: ms(LEARNED_FLOOR_MS),
                ceiling: ms(900)
            }
        );
        assert!(p(9).retry_writes);
        assert_eq!(p(4), UnitPolicy::of_line(&line.relay));
        assert_eq!(p(4).timeout, Timeout::Fixed(ms(400)));
        // Printed and read back the same.
        let again = parse(&crate::config::to_toml(&cfg), "again").unwrap();
        assert_eq!(again.lines[0].unit_tables, line.unit_tables);
        let said = line.unit_tables.describe(&line.relay);
        assert_eq!(
            said[0],
            "unit 1: response timeout 100 ms, pause 5 ms, 1 retries, writes not resent"
        );
        assert_eq!(
            said.last().unwrap(),
            "other units: response timeout 400 ms, pause 0 ms, 1 retries, writes not resent"
        );
    }

    #[test]
    fn bad_unit_tables_name_file_line_and_key() {
        let err = |units: &str| parse(&line_with(units), "t.toml").unwrap_err().to_string();
        let e = err("[[line.unit]]\nunits = \"1-3\"\n[[line.unit]]\nunits = 3\nretries = 1\n");
        assert!(
            e.starts_with("t.toml:7:9: line[0].unit[1].units: unit 3 is also in line[0].unit[0]"),
            "{e}"
        );
        let e = err("[[line.unit]]\nunits = 1\nresponse_timeout_ms = \"fast\"\n");
        assert!(
            e.starts_with(
                "t.toml:6:23: line[0].unit[0].response_timeout_ms: invalid value \"fast\""
            ),
            "{e}"
        );
        let e = err("[[line.unit]]\nunits = 1\nrespons_timeout_ms = 5\n");
        assert!(
            e.contains("line[0].unit[0].respons_timeout_ms: unknown key")
                && e.contains("did you mean `response_timeout_ms`"),
            "{e}"
        );
        let e = err("[[line.unit]]\nresponse_timeout_ms = 5\n");
        assert!(e.contains("line[0].unit[0].units: missing"), "{e}");
        let e = err("[[line.unit]]\nunits = \"5-2\"\n");
        assert!(e.contains("the range \"5-2\" is empty"), "{e}");
        let e = err("[[line.unit]]\nunits = 1\nresponse_timeout_max_ms = 500\n");
        assert!(
            e.contains("line[0].unit[0].response_timeout_max_ms: bounds a learned timeout"),
            "{e}"
        );
        let e = err("[[line.unit]]\nunits = 1\nresponse_timeout_ms = \"auto\"\nresponse_timeout_min_ms = 50\nresponse_timeout_max_ms = 40\n");
        assert!(
            e.contains("response_timeout_max_ms: must not be below"),
            "{e}"
        );
        let e = err("[[line.unit]]\nunits = 0\n");
        assert!(e.contains("must be between 1 and 255"), "{e}");
    }
}
