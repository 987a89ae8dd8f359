//! The configuration as TOML (`mbgate check-config`): either form of docs/design.md §4
//! and §4.1, every key with its value, which `parse` reads back to the same.

use super::{access, file, master, Config, Key, LineConfig, ListenConfig, Setting, KEYS};

/// The configuration as TOML, sections and keys in the order of docs/design.md §4
/// (`mbgate check-config`); a configuration the old form cannot say (several lines or
/// listeners, units, a device on TCP) in the form of §4.1. `parse(&to_toml(cfg), ..)`
/// gives back `cfg`.
pub fn to_toml(cfg: &Config) -> String {
    if !cfg.single_form() {
        return to_toml_lines(cfg);
    }
    let old: Vec<(&str, String)> = [
        "serial", "tcp", "relay", "log", "metrics", "capture", "control",
    ]
    .into_iter()
    // A file that only dials its masters writes no [tcp]: none is bound.
    .filter(|s| *s != "tcp" || !cfg.dial_only)
    .map(|s| (s, format!("[{s}]")))
    .collect();
    with_roles(print(cfg, &old), cfg)
}

/// `text` and then the `[[role]]` and `[[dial]]` tables, if any.
fn with_roles(text: String, cfg: &Config) -> String {
    let text = text + &super::dial::to_toml(&cfg.dials);
    if cfg.roles.is_empty() {
        return text;
    }
    format!("{text}\n{}", access::roles_to_toml(&cfg.roles))
}

/// The same configuration in the form of docs/design.md §4.1: a `[[line]]` for each
/// line (its units, its `serial` or `tcp` table, its `relay` table) and a `[[listen]]`
/// for each listener.
pub fn to_toml_lines(cfg: &Config) -> String {
    let mut out = Vec::new();
    for line in &cfg.lines {
        out.push(line_to_toml(line));
    }
    // With every line a master line no listener is bound, and none may be written;
    // a file that only dials its masters writes none.
    let listeners = match cfg.listens() {
        true => &cfg.listeners[..],
        false => &[],
    };
    for listener in listeners {
        out.push(listener_to_toml(listener, cfg));
    }
    out.push(print(
        cfg,
        &[
            ("log", "[log]".into()),
            ("metrics", "[metrics]".into()),
            ("capture", "[capture]".into()),
            ("control", "[control]".into()),
        ],
    ));
    with_roles(out.join("\n"), cfg)
}

/// A `[[line]]`: its role and units, its `serial` or `tcp` table, its routes, its
/// `relay` table and its `[[line.unit]]` tables.
fn line_to_toml(line: &LineConfig) -> String {
    let mut head = "[[line]]\n".to_owned();
    if line.master.is_some() {
        head += "role = \"master\"\n";
    }
    if !line.units.ids.is_empty() {
        head += &format!("units = {}\n", line.units.print_ids());
    }
    if !line.units.remap.is_empty() {
        head += &format!("remap = {}\n", line.units.print_remap());
    }
    let one = Config {
        lines: vec![line.clone()],
        ..Config::default()
    };
    let device = match &line.tcp {
        Some(address) => format!(
            "\n[line.tcp]\naddress = {}\nframing = {}\n{}",
            address.print(),
            line.serial.framing.print(),
            line.tcp_tls
                .as_ref()
                .map(access::device_to_toml)
                .unwrap_or_default()
        ),
        // A master line's serial table has only the keys a master line uses.
        None if line.master.is_some() => format!(
            "\n{}",
            print_keys(&one, "[line.serial]", |k| k.section == "serial" && k.master)
        ),
        None => format!("\n{}", print(&one, &[("serial", "[line.serial]".into())])),
    };
    let routes = match &line.master {
        Some(m) => master::to_toml(m).trim_start().to_owned() + "\n",
        None => String::new(),
    };
    let relay = match &line.master {
        // A master line's relay table has only the keys a master line uses.
        Some(_) => print_keys(&one, "[line.relay]", |k| k.section == "relay" && k.master),
        None => print(&one, &[("relay", "[line.relay]".into())]),
    };
    let units = line.unit_tables.to_toml();
    head + &device + "\n" + &routes + &relay + &units
}

/// A `[[listen]]`: its keys, framing, priority, transport, notifications and access.
fn listener_to_toml(listener: &ListenConfig, cfg: &Config) -> String {
    let one = Config {
        listeners: vec![listener.clone()],
        ..Config::default()
    };
    let table = print(&one, &[("tcp", "[[listen]]".into())]);
    let access = access::listen_to_toml(&listener.access, &cfg.roles);
    let mut priority = match listener.priority {
        0 => String::new(),
        p => format!("priority = {p}\n"),
    };
    if listener.transport != super::Transport::Tcp {
        priority += &format!("transport = {}\n", listener.transport.print());
    }
    if listener.notifications {
        priority += "notifications = true\n";
    }
    table + &format!("framing = {}\n", listener.framing.print()) + &priority + &access
}

/// Each of `tables`: its header, then the keys of its section (in a `[[listen]]`, as
/// that table calls them).
fn print(cfg: &Config, tables: &[(&str, String)]) -> String {
    let mut out = Vec::new();
    for (section, header) in tables {
        let listen = header == "[[listen]]";
        let rename = if listen { file::LISTEN_RENAMED } else { &[] };
        let mut table = format!("{header}\n");
        for key in KEYS.iter().filter(|k| k.section == *section) {
            let value = (key.get)(cfg);
            table += &format!("{} = {value}\n", file::renamed(rename, key.name));
        }
        out.push(table);
    }
    out.join("\n")
}

/// `header`, then the keys of [`KEYS`] that `which` takes.
fn print_keys(cfg: &Config, header: &str, which: impl Fn(&Key) -> bool) -> String {
    let mut table = format!("{header}\n");
    for key in KEYS.iter().filter(|k| which(k)) {
        table += &format!("{} = {}\n", key.name, (key.get)(cfg));
    }
    table
}
