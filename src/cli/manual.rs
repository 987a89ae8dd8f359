//! The man pages and shell completions, generated from the command line itself
//! (`mbgate generate`): mbgate(1) and one page per subcommand with clap_mangen, the
//! completion scripts with clap_complete, and mbgate.toml(5) from the commented
//! reference file `config/mbgate.toml` (its comments are the text of the page, so the
//! page and the file installed as /etc/mbgate/mbgate.toml say the same). The .deb ships
//! the output, kept in packaging/ and held to the command line by tests/packaging/docs.rs.

use clap_mangen::Man;
use roff::{bold, italic, roman, Roff};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// The commented reference configuration, the text of mbgate.toml(5).
const REFERENCE: &str = include_str!("../../config/mbgate.toml");

/// What every page's header names as its source and manual.
fn source() -> String {
    format!("mbgate {}", env!("CARGO_PKG_VERSION"))
}

const MANUAL: &str = "mbgate manual";

/// The sections every page of section 1 ends with.
fn see_also(roff: &mut Roff, page: &str) {
    let mut pages: Vec<String> = ["mbgate(1)", "mbgate.toml(5)"]
        .into_iter()
        .filter(|p| !p.starts_with(&format!("{page}(")))
        .map(str::to_owned)
        .collect();
    pages.push("systemctl(1)".into());
    roff.control("SH", ["SEE ALSO"]);
    roff.text([roman(pages.join(", "))]);
    roff.control("PP", []);
    roff.text([roman(
        "The user guide: /usr/share/doc/mbgate/README.md and /usr/share/doc/mbgate/docs/ \
         (docs/ in the source).",
    )]);
}

/// Writes mbgate(1), mbgate-SUBCOMMAND(1) for each subcommand, and mbgate.toml(5)
/// into `dir`; returns the files written.
pub(crate) fn man_pages(cmd: clap::Command, dir: &Path) -> io::Result<Vec<PathBuf>> {
    let mut cmd = cmd.disable_help_subcommand(true);
    cmd.build();
    let mut written = Vec::new();
    let mut page = |name: &str, section: &str, body: Vec<u8>| -> io::Result<()> {
        let path = dir.join(format!("{name}.{section}"));
        std::fs::write(&path, body)?;
        written.push(path);
        Ok(())
    };
    page("mbgate", "1", command_page(&cmd, "mbgate", true)?)?;
    for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set()) {
        let name = format!("mbgate-{}", sub.get_name());
        page(&name, "1", command_page(sub, &name, false)?)?;
    }
    page("mbgate.toml", "5", config_page().into_bytes())?;
    Ok(written)
}

/// One command's page: clap_mangen's sections, then exit status, files and see also.
fn command_page(cmd: &clap::Command, name: &str, top: bool) -> io::Result<Vec<u8>> {
    let man = Man::new(cmd.clone())
        .title(name.to_uppercase())
        .section("1")
        .source(source())
        .manual(MANUAL);
    let mut out = Vec::new();
    man.render_title(&mut out)?;
    man.render_name_section(&mut out)?;
    man.render_synopsis_section(&mut out)?;
    man.render_description_section(&mut out)?;
    if cmd.get_arguments().any(|a| !a.is_hide_set()) {
        man.render_options_section(&mut out)?;
    }
    if cmd.has_subcommands() {
        man.render_subcommands_section(&mut out)?;
    }
    let mut tail = Roff::new();
    if top {
        exit_status_and_signals(&mut tail);
    }
    tail.control("SH", ["FILES"]);
    for (file, what) in [
        (
            "/etc/mbgate/mbgate.toml",
            "the configuration of mbgate.service; see mbgate.toml(5)",
        ),
        (
            "/etc/mbgate/NAME.toml",
            "the configuration of the instance mbgate@NAME.service",
        ),
        (
            "/usr/share/doc/mbgate/examples/",
            "configurations of common setups, each checked with mbgate check-config",
        ),
    ] {
        tail.control("TP", [])
            .text([italic(file)])
            .text([roman(what)]);
    }
    see_also(&mut tail, name);
    tail.to_writer(&mut out)?;
    Ok(out)
}

/// The top page's exit codes and signals.
fn exit_status_and_signals(r: &mut Roff) {
    r.control("SH", ["EXIT STATUS"]);
    for (code, what) in [
        (
            "0",
            "a clean shutdown (SIGTERM or SIGINT: the requests on the line are answered first)",
        ),
        (
            "1",
            "any other failure at start, e.g. the listen address is in use",
        ),
        (
            "2",
            "a bad configuration or bad arguments; the message names the file, line and key",
        ),
    ] {
        r.control("TP", []).text([bold(code)]).text([roman(what)]);
    }
    // A paragraph of its own: run on after the last entry, it read as part of it.
    r.control("PP", []);
    r.text([roman(
        "The subcommands read, write and status have exit codes of their own: see their pages.",
    )]);
    r.control("SH", ["SIGNALS"]);
    for (signal, what) in [
        ("SIGTERM, SIGINT", "stop accepting, answer queued requests with 0x0A, wait for the ones on the line, exit 0"),
        ("SIGHUP", "reload the configuration file (mbgate run); the flags given at start stay on top"),
        ("SIGUSR1", "log the counters now"),
    ] {
        r.control("TP", []).text([bold(signal)]).text([roman(what)]);
    }
}

/// One key of the reference file: its table, name, value and the comment above it.
struct Documented {
    table: String,
    key: String,
    value: String,
    comment: Vec<String>,
}

/// The reference file read as: its opening comment, each key with its comment, and the
/// comment after the last key.
fn reference() -> (Vec<String>, Vec<Documented>, Vec<String>) {
    let (mut intro, mut keys, mut comment) = (Vec::new(), Vec::new(), Vec::new());
    let mut table = None;
    for line in REFERENCE.lines() {
        if let Some(text) = line.strip_prefix('#') {
            comment.push(text.strip_prefix(' ').unwrap_or(text).to_owned());
        } else if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            if table.is_none() {
                intro = std::mem::take(&mut comment);
            }
            comment.clear();
            table = Some(name.to_owned());
        } else if let (Some((key, value)), Some(t)) = (line.split_once(" = "), &table) {
            keys.push(Documented {
                table: t.clone(),
                key: key.trim().to_owned(),
                value: value.trim().to_owned(),
                comment: std::mem::take(&mut comment),
            });
        } else if line.trim().is_empty() && table.is_none() {
            comment.push(String::new());
        }
    }
    (intro, keys, comment)
}

/// A comment as roff: paragraphs of running text, indented lines (lists, examples)
/// kept as they are.
fn comment(roff: &mut Roff, lines: &[String]) {
    let mut text: Vec<&str> = Vec::new();
    let flush = |roff: &mut Roff, text: &mut Vec<&str>| {
        if !text.is_empty() {
            roff.text([roman(text.join(" "))]);
            text.clear();
        }
    };
    let mut verbatim = false;
    for line in lines {
        // Lists and examples are indented; commented-out TOML is a table or `key = `.
        let toml = line.split_once(" = ").is_some_and(|(k, _)| {
            !k.is_empty() && k.chars().all(|c| c.is_ascii_lowercase() || c == '_')
        });
        // A line of commented-out TOML that is itself a comment (`# # ...` in the
        // file) belongs to the example, verbatim: reflowed, it would no longer be TOML.
        let indented =
            line.starts_with("  ") || line.starts_with('[') || line.starts_with('#') || toml;
        if line.trim().is_empty() || line.trim_start().starts_with("---") {
            flush(roff, &mut text);
            if verbatim {
                roff.control("fi", []);
                verbatim = false;
            }
            roff.control("PP", []);
        } else if indented {
            flush(roff, &mut text);
            if !verbatim {
                roff.control("nf", []);
                verbatim = true;
            }
            roff.text([roman(line.clone())]);
        } else {
            if verbatim {
                roff.control("fi", []);
                verbatim = false;
            }
            text.push(line.trim());
        }
    }
    flush(roff, &mut text);
    if verbatim {
        roff.control("fi", []);
    }
}

/// mbgate.toml(5): the file's own comments, a key at a time, and the `[[line]]` form.
pub(crate) fn config_page() -> String {
    let (intro, keys, outro) = reference();
    let mut r = Roff::new();
    let source = source();
    r.control("TH", ["MBGATE.TOML", "5", "", &source, MANUAL]);
    r.control("SH", ["NAME"]);
    r.text([roman(
        "mbgate.toml - the configuration of mbgate, the Modbus/TCP to serial gateway",
    )]);
    r.control("SH", ["SYNOPSIS"]);
    r.text([
        italic("/etc/mbgate/mbgate.toml"),
        roman(" (mbgate.service)"),
    ]);
    r.text([
        line_break(),
        italic("/etc/mbgate/NAME.toml"),
        roman(" (mbgate@NAME.service)"),
    ]);
    r.control("SH", ["DESCRIPTION"]);
    // The file's title line is the page's NAME already.
    let intro = match intro.split_first() {
        Some((title, rest)) if title == "mbgate configuration" => rest,
        _ => &intro[..],
    };
    comment(&mut r, intro);
    keys_described(&mut r, &keys);
    r.control("SH", ["SEVERAL LINES AND LISTENERS"]);
    r.text([roman(
        "The same gateway can be written as device lines and listeners: a [[line]] table for \
         each line, a [[listen]] table for each listening address. A [[line]] has:",
    )]);
    for (key, what) in LINES_FORM {
        r.control("TP", []);
        r.text([bold(*key)]);
        r.text([roman(*what)]);
    }
    r.control("PP", []);
    r.text([roman(
        "A file uses one form or the other: [[line]] beside [serial] or [relay], or [[listen]] \
         beside [tcp], is refused. mbgate check-config FILE --lines prints any configuration \
         in this form. Errors name a table by its place: line[1].serial.baud_rate.",
    )]);
    r.control("SH", ["THE DEVICE AS MASTER"]);
    comment(&mut r, &outro);
    example(&mut r);
    see_also(&mut r, "mbgate.toml");
    r.render()
}

/// Each key of the file under its table's heading, with its comment (keys described
/// together with the one before them refer to it).
fn keys_described(r: &mut Roff, keys: &[Documented]) {
    let (mut table, mut described) = (String::new(), String::new());
    for k in keys {
        if k.table != table {
            table = k.table.clone();
            let heading = format!("[{table}]");
            r.control("SH", [heading.as_str()]);
        }
        r.control("TP", []);
        r.text([bold(k.key.clone()), roman(format!(" = {}", k.value))]);
        if k.comment.is_empty() {
            // Keys described together with the one before them.
            r.text([roman("See "), bold(described.clone()), roman(" above.")]);
        } else {
            comment(r, &k.comment);
            described = k.key.clone();
        }
    }
}

/// The page's example, and where the others are.
fn example(r: &mut Roff) {
    r.control("SH", ["EXAMPLE"]);
    r.text([roman(
        "One RTU bus at 9600 baud, 8E1, behind Modbus/TCP port 502:",
    )]);
    r.control("nf", []);
    r.control("RS", ["4"]);
    for line in [
        "[serial]",
        "path = \"/dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A1B2C3-if00-port0\"",
        "baud_rate = 9600",
        "parity = \"even\"",
        "flow_control = \"none\"",
        "framing = \"rtu\"",
    ] {
        r.text([roman(line)]);
    }
    r.control("RE", []);
    r.control("fi", []);
    r.control("PP", []);
    r.text([roman(
        "More, each a common setup: /usr/share/doc/mbgate/examples/. Check a file with mbgate \
         check-config FILE: it prints OK and the setup in a few lines, or the file, line and \
         key of the first error.",
    )]);
}

/// The keys of a `[[line]]`, a `[[listen]]` and a `[[line.route]]` (docs/design.md §4.1,
/// §4.2; docs/configuration.md).
const LINES_FORM: &[(&str, &str)] = &[
    ("units", "The unit ids whose requests go down this line: ids 1 to 255 and ranges written \"A-B\", e.g. units = [1, 2, \"20-29\"]. A single line without units or remap serves every unit."),
    ("remap", "The master's unit id to the id the device on this line answers to, e.g. remap = { 11 = 1 }: the master's unit 11 is unit 1 on this line, and its replies come back as unit 11."),
    ("serial", "The line's serial port: the keys of [serial], as a table [line.serial] or inline, serial = { path = \"/dev/ttyUSB1\", framing = \"rtu\" }."),
    ("tcp", "Instead of serial: a device on the network, tcp = { address = \"HOST:PORT\", framing = \"mbap\" } (a Modbus/TCP device that takes one connection, or a serial device server in raw TCP mode with framing rtu or ascii)."),
    ("relay", "The line's queueing and timing: the keys of [relay], as [line.relay]."),
    ("role", "\"master\": the device on this line is a Modbus master (a CIE-M10 in master mode, an RTU PLC); its requests go to Modbus/TCP slaves by the line's [[line.route]] tables."),
    ("[[line.route]]", "Of a master line: units (none: every other unit), and address = \"HOST:PORT\" (mbgate connects) or listen = \"ADDR\" (the slave connects in), response_timeout_ms (1000), max_in_flight (1)."),
    ("[[listen]]", "A listening address: the keys of [tcp], address standing for listen, and framing = \"mbap\" (Modbus/TCP, the default) or \"rtu\" (RTU over TCP). All listeners share all lines."),
];

fn line_break() -> roff::Inline {
    roff::line_break()
}

/// Writes the completion script for `shell` to `out`.
pub(crate) fn completion(
    mut cmd: clap::Command,
    shell: clap_complete::Shell,
    out: &mut dyn Write,
) -> io::Result<()> {
    clap_complete::generate(shell, &mut cmd, "mbgate", out);
    Ok(())
}
