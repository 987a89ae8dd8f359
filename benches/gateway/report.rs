//! The report: the rows and tables the scenarios add, rendered as Markdown, and how
//! their figures are written (µs, ms, %, the spread of some durations).

use std::fmt::Write as _;
use std::time::Duration;

#[derive(Default)]
pub(super) struct Report {
    rows: Vec<Row>,
    details: String,
}

struct Row {
    measure: String,
    figure: String,
    target: String,
    met: Option<bool>,
    scenario: &'static str,
}

impl Report {
    pub(super) fn row(
        &mut self,
        scenario: &'static str,
        measure: &str,
        figure: String,
        target: &str,
        met: Option<bool>,
    ) {
        eprintln!("  {measure}: {figure} (target {target})");
        self.rows.push(Row {
            measure: measure.into(),
            figure,
            target: target.into(),
            met,
            scenario,
        });
    }

    pub(super) fn detail(&mut self, title: &str, command: &str, table: &str) {
        let _ = write!(self.details, "#### {title}\n\n`{command}`\n\n{table}\n");
    }

    pub(super) fn render(&self, load_before: &str, load_after: &str) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "Load average (1, 5, 15 min) at start: {load_before}; at end: {load_after}.\n"
        );
        s += "| measure | figure | target | met | command |\n|---|---|---|---|---|\n";
        for r in &self.rows {
            let met = match r.met {
                Some(true) => "yes",
                Some(false) => "**no**",
                None => "-",
            };
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | `{}` |",
                r.measure,
                r.figure,
                r.target,
                met,
                command(r.scenario)
            );
        }
        s += "\n";
        s += &self.details;
        s
    }
}

pub(super) fn command(scenario: &str) -> String {
    format!("cargo bench --bench gateway -- {scenario}")
}

pub(super) fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

pub(super) fn us(d: Duration) -> String {
    format!("{:.1} µs", d.as_secs_f64() * 1e6)
}

pub(super) fn ms(d: Duration) -> String {
    format!("{:.2} ms", d.as_secs_f64() * 1e3)
}

pub(super) fn pct(x: f64) -> String {
    format!("{:.1} %", x * 100.0)
}

/// p50, p99 and max of some durations.
#[derive(Clone, Copy)]
pub(super) struct Spread {
    pub(super) p50: Duration,
    pub(super) p99: Duration,
    pub(super) max: Duration,
}

impl Spread {
    /// The three as Markdown table cells: `p50 | p99 | max`, in µs.
    pub(super) fn cells(&self) -> String {
        format!("{} | {} | {}", us(self.p50), us(self.p99), us(self.max))
    }
}

pub(super) fn spread(samples: &[Duration]) -> Spread {
    assert!(!samples.is_empty(), "no samples");
    let mut v = samples.to_vec();
    v.sort();
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    Spread {
        p50: at(0.50),
        p99: at(0.99),
        max: v[v.len() - 1],
    }
}

/// The signed difference b - a, in µs.
pub(super) fn diff_us(a: Duration, b: Duration) -> f64 {
    (b.as_secs_f64() - a.as_secs_f64()) * 1e6
}
