//! What a reload would change, key by key and line by line: the lines of the running
//! configuration and of the file matched by their identity (the serial port or the
//! device's address, never their place in the file), the changes a reload applies
//! taken into the running configuration, and every difference named as the log and
//! `mbgate reload` say it. Plain data: nothing here touches the gateway.

use crate::config::master::{MasterLine, Route};
use crate::config::{Config, LineConfig, ListenConfig, RelayConfig, Setting, Transport, KEYS};

/// The keys a reload applies while the gateway runs: of each line (`[relay]` or
/// `[line.relay]`), and of the gateway. Beside them a reload applies each
/// `[[line.unit]]` table, a master line's route timeouts, and the `priority` of each
/// `[[listen]]` and `[[role]]`.
pub(crate) const LINE_RELOADABLE: [&str; 4] = [
    "relay.response_timeout_ms",
    "relay.retries",
    "relay.retry_writes",
    "relay.probe_timeout_ms",
];
const GATEWAY_RELOADABLE: [&str; 4] = [
    "log.level",
    "log.traffic",
    "metrics.listen",
    "metrics.web_config",
];

/// What identifies a line across a reload: its serial port, or its device's address.
/// Two lines on one port or address are refused when the file is read.
pub(crate) fn identity(line: &LineConfig) -> &str {
    line.name()
}

/// For each line of `running`, the index of the line of `read` with its identity; or
/// why the two cannot be matched (a line is new or gone): a line is a relay task and
/// the route of its units, which only a restart makes or ends.
pub(crate) fn match_lines(
    running: &[LineConfig],
    read: &[LineConfig],
) -> Result<Vec<usize>, String> {
    let find = |lines: &[LineConfig], id: &str| lines.iter().position(|l| identity(l) == id);
    let gone: Vec<String> = running
        .iter()
        .filter(|l| find(read, identity(l)).is_none())
        .map(|l| format!("{:?}", identity(l)))
        .collect();
    let new: Vec<String> = read
        .iter()
        .filter(|l| find(running, identity(l)).is_none())
        .map(|l| format!("{:?}", identity(l)))
        .collect();
    let mut why = Vec::new();
    if !new.is_empty() {
        why.push(format!("the line on {} is new in the file", new.join(", ")));
    }
    if !gone.is_empty() {
        why.push(format!("the line on {} is gone from it", gone.join(", ")));
    }
    if !why.is_empty() {
        return Err(format!(
            "{}: a line is added or removed only by a restart (systemctl restart)",
            why.join(" and ")
        ));
    }
    Ok(running
        .iter()
        .map(|l| find(read, identity(l)).expect("matched above"))
        .collect())
}

/// `running` with what a reload applies taken from `read` (its lines matched by
/// `matched`, [`match_lines`]): each line's reloadable relay keys, the log and the
/// metrics listener. The rest stays as it runs.
pub(crate) fn merged(running: &Config, read: &Config, matched: &[usize]) -> Config {
    let mut c = running.clone();
    for (line, &j) in c.lines.iter_mut().zip(matched) {
        let read = &read.lines[j];
        retune(&mut line.relay, &read.relay);
        line.unit_tables = read.unit_tables.clone();
        if let (Some(m), Some(read)) = (&mut line.master, &read.master) {
            if timeouts_only(m, read) {
                *m = read.clone();
            }
        }
    }
    c.log = read.log.clone();
    c.metrics = read.metrics.clone();
    c.dials = read.dials.clone();
    // The UDP listeners are the file's; the TCP ones stay as they run.
    let udp = |l: &&ListenConfig| l.transport == Transport::Udp;
    c.listeners.retain(|l| !udp(&l));
    c.listeners
        .extend(read.listeners.iter().filter(udp).cloned());
    // Priority classes: each listener's (matched by its address), and the roles' when
    // nothing else of them changed.
    for l in &mut c.listeners {
        let read = read
            .listeners
            .iter()
            .find(|m| m.tcp.listen == l.tcp.listen && m.transport == l.transport);
        if let Some(m) = read {
            l.priority = m.priority;
        }
    }
    if same_roles_but_priority(running, read) {
        c.roles = read.roles.clone();
    }
    c
}

/// The reloadable keys of a line's relay table.
fn retune(into: &mut RelayConfig, from: &RelayConfig) {
    into.response_timeout_ms = from.response_timeout_ms;
    into.retries = from.retries;
    into.retry_writes = from.retry_writes;
    into.probe_timeout_ms = from.probe_timeout_ms;
}

/// Do two master lines' routes differ in their response timeouts alone? Those a
/// reload applies; any other change to the routes waits for a restart.
fn timeouts_only(a: &MasterLine, b: &MasterLine) -> bool {
    let same = |x: &Route, y: &Route| {
        let x = Route {
            response_timeout_ms: y.response_timeout_ms,
            ..x.clone()
        };
        x == *y
    };
    a.routes.len() == b.routes.len() && a.routes.iter().zip(&b.routes).all(|(x, y)| same(x, y))
}

/// One difference between two configurations.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Change {
    /// How it is said: `relay.retries = 2`, `line "/dev/ttyUSB1" relay.retries = 2`.
    pub(crate) said: String,
    /// Does a reload apply it?
    pub(crate) reloadable: bool,
}

/// Every difference from `a` to `b` (their lines matched by `matched`), in the order
/// of `a`'s lines, then the gateway's sections. With `[[line]]` tables each line's
/// keys are named with the line (`line "/dev/ttyUSB1" relay.retries = 2`); in the
/// old form, the one line's are the `[serial]` and `[relay]` keys as they are.
pub(crate) fn changes(a: &Config, b: &Config, matched: &[usize]) -> Vec<Change> {
    let named = !(a.single_line() && b.single_line());
    let mut out = Vec::new();
    for (la, &j) in a.lines.iter().zip(matched) {
        let prefix = if named {
            format!("line {:?} ", identity(la))
        } else {
            String::new()
        };
        out.extend(line_changes(la, &b.lines[j], &prefix));
    }
    for k in KEYS
        .iter()
        .filter(|k| ["log", "metrics", "capture", "control"].contains(&k.section))
    {
        let (va, vb) = ((k.get)(a), (k.get)(b));
        if va != vb {
            let key = format!("{}.{}", k.section, k.name);
            let reloadable = GATEWAY_RELOADABLE.contains(&key.as_str());
            out.push(Change {
                said: format!("{key} = {vb}"),
                reloadable,
            });
        }
    }
    out.extend(listener_changes(a, b));
    out.extend(dial_changes(a, b));
    out.extend(role_changes(a, b));
    out
}

/// One line's differences from `la` to `lb`, each said after `prefix`.
fn line_changes(la: &LineConfig, lb: &LineConfig, prefix: &str) -> Vec<Change> {
    let mut out = Vec::new();
    let mut say = |key: &str, value: String, reloadable: bool| {
        out.push(Change {
            said: format!("{prefix}{key} = {value}"),
            reloadable,
        })
    };
    if la.units.ids != lb.units.ids {
        say("units", lb.units.print_ids(), false);
    }
    if la.units.remap != lb.units.remap {
        say("remap", lb.units.print_remap(), false);
    }
    let (ca, cb) = (line_as_config(la), line_as_config(lb));
    for k in KEYS
        .iter()
        .filter(|k| ["serial", "relay"].contains(&k.section))
    {
        let (va, vb) = ((k.get)(&ca), (k.get)(&cb));
        if va != vb {
            let key = format!("{}.{}", k.section, k.name);
            let reloadable = LINE_RELOADABLE.contains(&key.as_str());
            say(&key, vb, reloadable);
        }
    }
    // Each unit whose [[line.unit]] table changed, with its settings as they are
    // now (a reload applies them).
    for u in unit_tables_changed(la, lb) {
        let now = lb.unit_tables.policy(&lb.relay, u).describe();
        say(&format!("unit {u}"), now, true);
    }
    match (&la.master, &lb.master) {
        (Some(a), Some(b)) if timeouts_only(a, b) => {
            for (i, (ra, rb)) in a.routes.iter().zip(&b.routes).enumerate() {
                if ra.response_timeout_ms != rb.response_timeout_ms {
                    let key = format!("route[{i}].response_timeout_ms");
                    say(&key, rb.response_timeout_ms.to_string(), true);
                }
            }
        }
        (a, b) if a != b => say("route", "(the [[line.route]] tables)".into(), false),
        _ => {}
    }
    if la.tcp_tls != lb.tcp_tls {
        say("tcp.tls", "(the device's TLS settings)".into(), false);
    }
    out
}

/// The units, in order, whose `[[line.unit]]` settings differ from `la` to `lb`.
fn unit_tables_changed(la: &LineConfig, lb: &LineConfig) -> Vec<u8> {
    let named = |l: &LineConfig| -> Vec<u8> {
        l.unit_tables
            .0
            .iter()
            .flat_map(|t| t.ids.iter().copied())
            .collect()
    };
    let mut units = named(la);
    units.extend(named(lb));
    units.sort_unstable();
    units.dedup();
    units.retain(|&u| la.unit_tables.settings(u) != lb.unit_tables.settings(u));
    units
}

/// The `[[role]]` tables' differences: a priority is applied, anything else waits
/// for a restart.
fn role_changes(a: &Config, b: &Config) -> Vec<Change> {
    if !same_roles_but_priority(a, b) {
        return vec![Change {
            said: "the [[role]] tables".into(),
            reloadable: false,
        }];
    }
    let mut out = Vec::new();
    for (ra, rb) in a.roles.iter().zip(&b.roles) {
        if ra.priority != rb.priority {
            let class = rb
                .priority
                .map_or("(the listener's)".into(), |p| p.to_string());
            out.push(Change {
                said: format!("role {:?} priority = {class}", rb.name),
                reloadable: true,
            });
        }
    }
    out
}

/// Do the two configurations' `[[role]]` tables differ in their `priority` alone?
/// That a reload applies; any other change to them waits for a restart.
fn same_roles_but_priority(a: &Config, b: &Config) -> bool {
    a.roles.len() == b.roles.len()
        && a.roles.iter().zip(&b.roles).all(|(x, y)| {
            let x = crate::config::AccessRole {
                priority: y.priority,
                ..x.clone()
            };
            x == *y
        })
}

/// The dials' differences, each applied (docs/dialing.md "Reload"): matched by their
/// address, one gone stops, one new starts, one changed dials again.
fn dial_changes(a: &Config, b: &Config) -> Vec<Change> {
    let applied = |said: String| Change {
        said,
        reloadable: true,
    };
    let mut out = Vec::new();
    for d in &a.dials {
        match b.dials.iter().find(|e| e.address == d.address) {
            None => out.push(applied(format!("dial \"{}\" removed", d.address))),
            Some(e) if e != d => out.push(applied(format!(
                "dial \"{}\" changed (dialing again)",
                d.address
            ))),
            Some(_) => {}
        }
    }
    for e in b
        .dials
        .iter()
        .filter(|e| !a.dials.iter().any(|d| d.address == e.address))
    {
        out.push(applied(format!("dial \"{}\" added", e.address)));
    }
    out
}

/// A line's settings as a configuration of the single-line form, to read its keys by
/// [`KEYS`].
fn line_as_config(line: &LineConfig) -> Config {
    Config {
        lines: vec![line.clone()],
        ..Config::default()
    }
}

/// The listeners' differences (all of them wait for a restart): `tcp.*` keys in the old
/// form; with `[[listen]]` tables each listener by its address.
fn listener_changes(a: &Config, b: &Config) -> Vec<Change> {
    let restart = |said: String| Change {
        said,
        reloadable: false,
    };
    let keys = || KEYS.iter().filter(|k| k.section == "tcp");
    let mut out = Vec::new();
    // A file that only dials its masters binds no listener (docs/dialing.md).
    if a.dial_only != b.dial_only {
        out.push(restart(match b.dial_only {
            true => "no listener: the file only dials its masters".into(),
            false => "a listener: the file names one".into(),
        }));
    }
    if a.single_listener() && b.single_listener() {
        out.extend(
            keys()
                .filter(|k| (k.get)(a) != (k.get)(b))
                .map(|k| restart(format!("tcp.{} = {}", k.name, (k.get)(b)))),
        );
        return out;
    }
    let (la, lb) = (&a.listeners, &b.listeners);
    let at = |l: &ListenConfig| l.tcp.listen;
    let same = |l: &ListenConfig, m: &ListenConfig| at(l) == at(m) && l.transport == m.transport;
    // A UDP listener is added, removed or changed by a reload (docs/dialing.md).
    let named = |l: &ListenConfig| match l.transport {
        Transport::Udp => format!("{} (UDP)", at(l)),
        Transport::Tcp => at(l).to_string(),
    };
    let said = |l: &ListenConfig, what: String| Change {
        said: format!("listen \"{}\" {what}", named(l)),
        reloadable: l.transport == Transport::Udp,
    };
    for l in la {
        match lb.iter().find(|m| same(l, m)) {
            None => out.push(said(l, "(gone from the file)".into())),
            Some(m) if l.transport == Transport::Udp => {
                if l != m {
                    out.push(said(m, "changed (started again)".into()));
                }
            }
            Some(m) => out.extend(tcp_listener_changes(l, m)),
        }
    }
    for m in lb.iter().filter(|m| !la.iter().any(|l| same(l, m))) {
        out.push(said(m, "(new in the file)".into()));
    }
    out
}

/// A TCP listener's differences, matched by its address: all wait for a restart
/// but its priority.
fn tcp_listener_changes(l: &ListenConfig, m: &ListenConfig) -> Vec<Change> {
    let restart = |said: String| Change {
        said,
        reloadable: false,
    };
    let at = |l: &ListenConfig| l.tcp.listen;
    let as_config = |l: &ListenConfig| Config {
        listeners: vec![l.clone()],
        ..Config::default()
    };
    let mut out = Vec::new();
    let (ca, cb) = (as_config(l), as_config(m));
    for k in KEYS
        .iter()
        .filter(|k| k.section == "tcp")
        .filter(|k| k.name != "listen")
    {
        if (k.get)(&ca) != (k.get)(&cb) {
            let said = format!("listen \"{}\" {} = {}", at(l), k.name, (k.get)(&cb));
            out.push(restart(said));
        }
    }
    if l.framing != m.framing {
        let said = format!("listen \"{}\" framing = {}", at(l), m.framing.print());
        out.push(restart(said));
    }
    if l.priority != m.priority {
        out.push(Change {
            said: format!("listen \"{}\" priority = {}", at(l), m.priority),
            reloadable: true,
        });
    }
    // Who may connect and what they may do (docs/security.md); the
    // certificate files themselves are read again by every reload.
    if l.access != m.access {
        let said = format!(
            "listen \"{}\" access (allow, read_only, write or tls)",
            at(l)
        );
        out.push(restart(said));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_lines(first: (&str, u32), second: (&str, u32)) -> Config {
        let line = |(path, timeout): (&str, u32), unit: u8| {
            format!(
                "[[line]]\nunits = [{unit}]\nserial = {{ path = \"{path}\" }}\nrelay = {{ response_timeout_ms = {timeout} }}\n"
            )
        };
        let text = line(first, 1) + &line(second, 2);
        crate::config::parse(&text, "t").unwrap()
    }

    /// The same two lines written in the other order: nothing changes but the units
    /// each table lists (which stay as they run); each line keeps its own timeout.
    #[test]
    fn lines_are_matched_by_their_port_not_their_place() {
        let running = two_lines(("/dev/a", 100), ("/dev/b", 200));
        let read = two_lines(("/dev/b", 200), ("/dev/a", 100));
        let matched = match_lines(&running.lines, &read.lines).unwrap();
        assert_eq!(matched, [1, 0]);
        let new = merged(&running, &read, &matched);
        assert_eq!(new, running, "nothing a reload applies changed");
        let said: Vec<String> = changes(&running, &read, &matched)
            .into_iter()
            .map(|c| c.said)
            .collect();
        assert_eq!(
            said,
            [
                r#"line "/dev/a" units = [2]"#,
                r#"line "/dev/b" units = [1]"#
            ]
        );

        // One line's timeout changed: that line's, named, and applied.
        let read = two_lines(("/dev/b", 300), ("/dev/a", 100));
        let matched = match_lines(&running.lines, &read.lines).unwrap();
        let new = merged(&running, &read, &matched);
        let timeouts: Vec<u64> = new
            .lines
            .iter()
            .map(|l| l.relay.response_timeout_ms)
            .collect();
        assert_eq!(timeouts, [100, 300]);
        assert_eq!(
            changes(&running, &new, &[0, 1]),
            [Change {
                said: r#"line "/dev/b" relay.response_timeout_ms = 300"#.into(),
                reloadable: true
            }]
        );
    }

    /// A master line beside a line of slaves: its routes' timeouts are applied and
    /// named by route; another change to its routes waits for a restart.
    #[test]
    fn a_master_lines_route_timeouts_are_applied() {
        let file = |timeout: u32, address: &str| {
            let text = format!(
                "[[line]]\nrole = \"master\"\nserial = {{ path = \"/dev/m\" }}\n\
                 [[line.route]]\naddress = \"{address}\"\nresponse_timeout_ms = {timeout}\n\
                 [[line]]\nunits = [1]\nserial = {{ path = \"/dev/s\" }}\n"
            );
            crate::config::parse(&text, "t").unwrap()
        };
        let running = file(300, "h:1");
        let read = file(900, "h:1");
        let matched = match_lines(&running.lines, &read.lines).unwrap();
        let new = merged(&running, &read, &matched);
        assert_eq!(new, read, "the timeout taken");
        assert_eq!(
            changes(&running, &new, &matched),
            [Change {
                said: r#"line "/dev/m" route[0].response_timeout_ms = 900"#.into(),
                reloadable: true
            }]
        );
        let moved = file(900, "h:2");
        let new = merged(&running, &moved, &matched);
        assert_eq!(new, running, "the route's slave moved: nothing applied");
        assert_eq!(
            changes(&new, &moved, &matched),
            [Change {
                said: r#"line "/dev/m" route = (the [[line.route]] tables)"#.into(),
                reloadable: false
            }]
        );
    }

    /// A master line alone (the old form's one line): its route timeouts applied too.
    #[test]
    fn a_lone_master_lines_route_timeouts_are_applied() {
        let file = |timeout: u32| {
            let text = format!(
                "[[line]]\nrole = \"master\"\nserial = {{ path = \"/dev/m\" }}\n\
                 [[line.route]]\naddress = \"h:1\"\nresponse_timeout_ms = {timeout}\n"
            );
            crate::config::parse(&text, "t").unwrap()
        };
        let (running, read) = (file(300), file(900));
        assert!(running.single_line(), "the single-line form");
        let matched = match_lines(&running.lines, &read.lines).unwrap();
        let new = merged(&running, &read, &matched);
        assert_eq!(new, read);
        let said: Vec<String> = changes(&running, &new, &matched)
            .into_iter()
            .map(|c| c.said)
            .collect();
        assert_eq!(said, ["route[0].response_timeout_ms = 900"]);
    }

    #[test]
    fn a_line_new_or_gone_is_named() {
        let running = two_lines(("/dev/a", 100), ("/dev/b", 200));
        let read = two_lines(("/dev/a", 100), ("/dev/c", 200));
        assert_eq!(
            match_lines(&running.lines, &read.lines),
            Err(r#"the line on "/dev/c" is new in the file and the line on "/dev/b" is gone from it: a line is added or removed only by a restart (systemctl restart)"#.into())
        );
    }

    /// Every key changed but the port (and `serial.direction`, which cannot go with
    /// the `rs485 = true` the file has): the reloadable ones are exactly those applied;
    /// the old form's keys are named as they are, without a line.
    #[test]
    fn a_reload_takes_exactly_the_reloadable_keys() {
        let read = super::super::tests::all_changed();
        let mut running = Config::default();
        running.lines[0].serial.path = read.lines[0].serial.path.clone();
        let matched = match_lines(&running.lines, &read.lines).unwrap();
        let all = changes(&running, &read, &matched);
        assert_eq!(
            all.len(),
            KEYS.len() - 2,
            "every key but the port and the direction: {all:#?}"
        );
        let new = merged(&running, &read, &matched);
        let taken: Vec<String> = changes(&running, &new, &[0])
            .into_iter()
            .map(|c| c.said.split(" = ").next().unwrap().to_owned())
            .collect();
        let reloadable: Vec<&str> = LINE_RELOADABLE
            .iter()
            .chain(&GATEWAY_RELOADABLE)
            .copied()
            .collect();
        assert_eq!(taken, reloadable);
        assert!(changes(&running, &new, &[0]).iter().all(|c| c.reloadable));
        assert!(changes(&new, &read, &matched).iter().all(|c| !c.reloadable));
    }

    /// A unit's table changed, or a table was added to the old form's one line: the
    /// units named with their settings as they are now, applied by the reload.
    #[test]
    fn unit_tables_are_applied_and_each_unit_named() {
        let file = |units: &str| {
            let text =
                format!("[[line]]\nserial = {{ path = \"/dev/a\", framing = \"rtu\" }}\n{units}");
            crate::config::parse(&text, "t").unwrap()
        };
        let running = file("");
        assert!(running.single_line(), "the single-line form");
        let read = file("[[line.unit]]\nunits = \"1-2\"\nresponse_timeout_ms = 100\n");
        let matched = match_lines(&running.lines, &read.lines).unwrap();
        let new = merged(&running, &read, &matched);
        assert_eq!(new.lines[0].unit_tables, read.lines[0].unit_tables);
        let said: Vec<(String, bool)> = changes(&running, &new, &[0])
            .into_iter()
            .map(|c| (c.said, c.reloadable))
            .collect();
        let unit = |u| {
            let s = format!("line \"/dev/a\" unit {u} = response timeout 100 ms, pause 0 ms, 0 retries, writes not resent");
            (s, true)
        };
        assert_eq!(said, [unit(1), unit(2)]);
        assert!(
            changes(&new, &read, &matched).is_empty(),
            "nothing waits for a restart"
        );
        // Back to the line's settings.
        let back = merged(&new, &running, &matched);
        assert!(back.lines[0].unit_tables.is_empty());
    }

    /// Every key a `[[listen]]` or a `[[role]]` declares (their own and `[tcp]`'s,
    /// read from the declarations, so a key added later without a value here fails):
    /// changed alone in the file, a reload names it, and one it says it applies is
    /// in the running configuration after it, none left to name; one it does not
    /// apply is named as waiting for a restart.
    #[test]
    fn every_listener_and_role_key_changed_is_applied_or_named() {
        use crate::config::access::{LISTEN_KEYS, ROLE_KEYS};
        // A value other than the default for each key.
        let listen_value = |key: &str| -> Option<&str> {
            Some(match key {
                "framing" => "\"rtu\"",
                "allow" => "[\"10.0.0.0/8\"]",
                "read_only" => "true",
                "write" => "[{ units = [1] }]",
                "tls" => "{ cert = \"c.pem\", key = \"k.pem\", client_ca = \"ca.pem\" }",
                "priority" => "3",
                "transport" => "\"udp\"",
                // A UDP listener's only.
                "notifications" => "true\ntransport = \"udp\"",
                "max_connections" => "9",
                "idle_timeout_ms" => "77",
                _ => return None,
            })
        };
        let role_value = |key: &str| -> Option<&str> {
            Some(match key {
                "read_only" => "true",
                "write" => "[{ units = [1] }]",
                "priority" => "5",
                _ => return None,
            })
        };
        let file = |listen: &str, role: &str| {
            let text = format!(
                "[[line]]\nserial = {{ path = \"/dev/a\" }}\n\
                 [[listen]]\naddress = \"127.0.0.1:5020\"\n{listen}\n\
                 [[role]]\nname = \"r\"\n{role}\n"
            );
            crate::config::parse(&text, "t").unwrap_or_else(|e| panic!("{text}: {e}"))
        };
        let running = file("", "");
        let mut keys: Vec<(&str, String, bool)> = Vec::new();
        let tcp = KEYS
            .iter()
            .filter(|k| k.section == "tcp" && k.name != "listen");
        for name in LISTEN_KEYS
            .iter()
            .map(|k| k.name)
            .chain(tcp.map(|k| k.name))
        {
            let v = listen_value(name).unwrap_or_else(|| panic!("no value for listen.{name}"));
            keys.push((name, format!("{name} = {v}"), true));
        }
        for name in ROLE_KEYS.iter().map(|k| k.name).filter(|&n| n != "name") {
            let v = role_value(name).unwrap_or_else(|| panic!("no value for role.{name}"));
            keys.push((name, format!("{name} = {v}"), false));
        }
        for (name, line, listener) in keys {
            let read = if listener {
                file(&line, "")
            } else {
                file("", &line)
            };
            let matched = match_lines(&running.lines, &read.lines).unwrap();
            let all = changes(&running, &read, &matched);
            assert!(!all.is_empty(), "{line}: not named by a reload");
            let new = merged(&running, &read, &matched);
            let left = changes(&new, &read, &matched);
            for c in &all {
                if c.reloadable {
                    assert!(
                        !left.iter().any(|l| l.said == c.said),
                        "{line}: said applied ({}), not applied",
                        c.said
                    );
                } else {
                    assert!(
                        left.contains(c),
                        "{line}: {} not waiting for a restart",
                        c.said
                    );
                }
            }
            if name == "priority" {
                assert!(all.iter().all(|c| c.reloadable), "{line}: {all:?}");
                let source = &running.listeners[0];
                let class = new.priority_of(source, Some("r"));
                assert_eq!(class, if listener { 3 } else { 5 }, "{line}");
                let class = new.priority_of(source, None);
                assert_eq!(class, if listener { 3 } else { 0 }, "{line}");
            }
        }
    }

    /// A file that only dials its masters binds no listener: one that names a
    /// listener after it, or stops naming one, waits for a restart, and says so.
    #[test]
    fn a_listener_opened_or_closed_beside_the_dials_waits_for_a_restart() {
        let dial = "[[dial]]\naddress = \"scada.example.net:502\"\n";
        let only =
            crate::config::parse(&format!("[serial]\npath = \"/dev/a\"\n{dial}"), "t").unwrap();
        let named = crate::config::parse(
            &format!("[serial]\npath = \"/dev/a\"\n[tcp]\nlisten = \"0.0.0.0:502\"\n{dial}"),
            "t",
        )
        .unwrap();
        for (a, b, said) in [
            (&only, &named, "a listener: the file names one"),
            (
                &named,
                &only,
                "no listener: the file only dials its masters",
            ),
        ] {
            let all = changes(a, b, &[0]);
            assert_eq!(
                all,
                vec![Change {
                    said: said.into(),
                    reloadable: false
                }]
            );
            let new = merged(a, b, &[0]);
            assert_eq!(new.dial_only, a.dial_only, "as it runs");
        }
    }
}
