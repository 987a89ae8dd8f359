//! The README and the user guide in docs/ as a user meets them, and what the package
//! ships beside them:
//!
//! - every command runs from a checkout as printed: the blocks marked `<!-- run -->` are
//!   run, line by line (`... &` in the background), against the output shown after
//!   them (numbers with a decimal point, such as times, may differ); every other
//!   command is of a form that runs: the binary named as the build puts it
//!   (`target/release/mbgate`, or `cargo run --release --`), its subcommand and every
//!   flag real, the scripts and files it names present; a bare `mbgate` only in a block
//!   for a machine with the package installed (first line `# with the .deb installed`);
//! - every link and anchor leads somewhere;
//! - every example configuration passes `check-config`, is named in the guide, and a
//!   copy of it in the guide is the file;
//! - the man pages and completions in packaging/ are what `mbgate generate` gives now,
//!   the pages render without a warning, and each shell loads its completions;
//! - docs/architecture.md and CONTRIBUTING.md name only files, modules and types the
//!   tree has, every file of src/ is on the map, every import points down the rooms'
//!   drawing, and the files a new framing touches are counted right (`docs/map.rs`);
//!   the files its "Who does what" names for clap, signal handlers and unsafe blocks
//!   are the code's (`docs/claims.rs`);
//! - no production function of src/ is over 60 lines unless it says why, and no
//!   production file over 600 (`docs/length.rs`);
//! - what src/ declares `pub` is named outside the library or by a public interface
//!   (`docs/surface.rs`).
//!
//! The examples listen on fixed ports (5502, 1502, ...), as a user's would: they run one
//! at a time.

use crate::common;
mod claims;
mod length;
mod map;
mod surface;

use common::{peer, repo};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Mutex;
use std::thread;
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_mbgate");
/// What marks a block for a machine with the package installed.
const INSTALLED: &str = "# with the .deb installed";
/// Programs a command may start with, besides mbgate and the scripts.
const PROGRAMS: &[&str] = &[
    "cargo",
    "sleep",
    "socat",
    "sudo",
    "sudoedit",
    "systemctl",
    "journalctl",
    "cp",
    "curl",
    "man",
    "rustup",
    "apt",
    "apt-get",
    "cross",
    "kill",
    // docs/security.md's recipe, run by `the_security_recipe_makes_certificates_the_gateway_takes`.
    "openssl",
    "mkdir",
    "printf",
    "chmod",
    // docs/capture.md's displays of a capture file, and where a live one goes.
    "tshark",
    "wireshark",
    "grep",
    "cd",
    // docs/install.md: a static binary checked and installed, the container image loaded.
    "sha256sum",
    "install",
    "sed",
    "tee",
    "docker",
    // docs/watching.md: the alert rules checked and tested, as tests/e2e/alerts.rs does.
    "promtool",
];

/// The README, CONTRIBUTING.md and every page of docs/.
fn pages() -> Vec<PathBuf> {
    let mut pages = vec![repo().join("README.md"), repo().join("CONTRIBUTING.md")];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(repo().join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.sort();
    pages.extend(docs);
    pages
}

fn name(page: &Path) -> String {
    page.strip_prefix(repo()).unwrap().display().to_string()
}

/// A fenced block of a page.
#[derive(Debug, Clone)]
struct Block {
    lang: String,
    text: String,
    /// Its line in the page (1-based), for messages.
    line: usize,
    /// Marked `<!-- run -->`.
    run: bool,
    /// The `text` block right after it, if any.
    expected: Option<String>,
}

/// The fenced blocks of `md`, fences possibly indented (in a list item).
fn blocks(md: &str) -> Vec<Block> {
    let lines: Vec<&str> = md.lines().collect();
    let mut out: Vec<Block> = Vec::new();
    // Where each block ended, to find a text block right after the one before.
    let mut ends: Vec<usize> = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let trimmed = lines[i].trim_start();
        if let Some(lang) = trimmed.strip_prefix("```") {
            let indent = lines[i].len() - trimmed.len();
            let start = i;
            let mut text = String::new();
            i += 1;
            while i < lines.len() && !lines[i].trim_start().starts_with("```") {
                let l = lines[i];
                text += l
                    .get(indent.min(l.len() - l.trim_start().len())..)
                    .unwrap_or("");
                text.push('\n');
                i += 1;
            }
            let before = lines[..start]
                .iter()
                .rev()
                .find(|l| !l.trim().is_empty())
                .map(|l| l.trim());
            let block = Block {
                lang: lang.trim().to_owned(),
                text,
                line: start + 1,
                run: before == Some("<!-- run -->"),
                expected: None,
            };
            // A text block right after the previous block is its expected output.
            if block.lang == "text" {
                if let (Some(prev), Some(&end)) = (out.last_mut(), ends.last()) {
                    let between = &lines[end + 1..start];
                    if prev.lang == "sh" && between.iter().all(|l| l.trim().is_empty()) {
                        prev.expected = Some(block.text.clone());
                    }
                }
            }
            out.push(block);
            ends.push(i);
        }
        i += 1;
    }
    out
}

/// The commands of a shell block: continued lines joined, comments kept apart.
fn commands(text: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut pending = String::new();
    for line in text.lines() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        if let Some(head) = line.strip_suffix('\\') {
            pending += head;
            pending.push(' ');
            continue;
        }
        pending += line;
        let (cmd, comment) = split_comment(&pending);
        out.push((cmd.trim().to_owned(), comment.trim().to_owned()));
        pending.clear();
    }
    out
}

/// `cmd # comment` → (cmd, comment), a `#` outside quotes after a space.
fn split_comment(line: &str) -> (&str, &str) {
    let (mut single, mut double) = (false, false);
    let bytes = line.as_bytes();
    for (i, &b) in bytes.iter().enumerate() {
        match b {
            b'\'' if !double => single = !single,
            b'"' if !single => double = !double,
            b'#' if !single && !double && i > 0 && bytes[i - 1] == b' ' => {
                return (&line[..i], &line[i + 1..]);
            }
            _ => {}
        }
    }
    (line, "")
}

/// `--help` of an mbgate subcommand (`["generate", "man"]`), cached.
fn help(path: &[String], cache: &mut BTreeMap<Vec<String>, Option<String>>) -> Option<String> {
    cache
        .entry(path.to_vec())
        .or_insert_with(|| {
            let out = Command::new(BIN).args(path).arg("--help").output().unwrap();
            out.status
                .success()
                .then(|| String::from_utf8_lossy(&out.stdout).into_owned())
        })
        .clone()
}

/// Whether `cmd` is of a form that runs from a checkout (or, with `installed`, on a
/// machine with the package installed); why not, if not.
fn runnable(
    cmd: &str,
    installed: bool,
    cache: &mut BTreeMap<Vec<String>, Option<String>>,
) -> Result<(), String> {
    pipeline(cmd)
        .into_iter()
        .try_for_each(|part| runnable_one(part, installed, cache))
}

/// The commands of a pipeline or list (`a | b`, `a && b`, `a; b`), split outside quotes.
fn pipeline(cmd: &str) -> Vec<&str> {
    let (mut single, mut double) = (false, false);
    let (mut parts, mut start) = (Vec::new(), 0);
    let bytes = cmd.as_bytes();
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'\'' if !double => single = !single,
            b'"' if !single => double = !double,
            b'|' | b';' if !single && !double => {
                parts.push(&cmd[start..i]);
                start = i + 1;
            }
            b'&' if !single && !double && bytes.get(i + 1) == Some(&b'&') => {
                parts.push(&cmd[start..i]);
                start = i + 2;
                i += 1;
            }
            _ => {}
        }
        i += 1;
    }
    parts.push(&cmd[start..]);
    parts
}

/// [`runnable`] for one simple command.
fn runnable_one(
    cmd: &str,
    installed: bool,
    cache: &mut BTreeMap<Vec<String>, Option<String>>,
) -> Result<(), String> {
    let words: Vec<&str> = cmd.trim_end_matches('&').split_whitespace().collect();
    let mut rest: &[&str] = &words;
    // `sudo`, and variables set for the command.
    while let Some((first, tail)) = rest.split_first() {
        if *first == "sudo" || (first.contains('=') && !first.starts_with('-')) {
            rest = tail;
        } else {
            break;
        }
    }
    let Some((&program, args)) = rest.split_first() else {
        return Ok(());
    };
    let mbgate_args = match program {
        "target/release/mbgate" if installed => {
            return Err(format!(
                "a block starting with `{INSTALLED}` runs the packaged `mbgate`, not a checkout's"
            ))
        }
        "target/release/mbgate" => Some(args),
        "mbgate" if installed => Some(args),
        // Where docs/install.md puts a static binary.
        "/usr/local/bin/mbgate" => Some(args),
        "mbgate" => {
            return Err(format!(
                "`mbgate` is not on PATH in a checkout: `target/release/mbgate`, or a block \
                 starting with `{INSTALLED}`"
            ))
        }
        "cargo" if args.starts_with(&["run", "--release", "--"]) => Some(&args[3..]),
        _ => None,
    };
    for word in args {
        let path = word.trim_matches(|c| c == '"' || c == '\'');
        let in_repo = ["config/", "docs/", "scripts/", "systemd/"]
            .iter()
            .any(|p| path.starts_with(p));
        if in_repo && !path.contains('*') && !repo().join(path).exists() {
            return Err(format!("{path} does not exist"));
        }
    }
    if let Some(args) = mbgate_args {
        let mut path: Vec<String> = Vec::new();
        let mut text = help(&path, cache).unwrap();
        // The subcommand (and generate's own), then its flags.
        for word in args.iter().take(2) {
            if word.starts_with('-') {
                break;
            }
            let mut deeper = path.clone();
            deeper.push((*word).to_owned());
            match help(&deeper, cache) {
                Some(t) => {
                    path = deeper;
                    text = t;
                }
                None if path.is_empty() => return Err(format!("no subcommand {word}")),
                None => break,
            }
        }
        for word in args {
            let flag = word.split('=').next().unwrap();
            if !flag.starts_with('-') || flag == "-" {
                continue;
            }
            let known = [" ", ",", "\n", "="]
                .iter()
                .any(|end| text.contains(&format!("{flag}{end}")));
            if !known {
                return Err(format!("mbgate {} has no flag {flag}", path.join(" ")));
            }
        }
        return Ok(());
    }
    if let Some(script) = program.strip_prefix("scripts/") {
        let file = repo().join("scripts").join(script);
        return if file.is_file() {
            Ok(())
        } else {
            Err(format!("no script {program}"))
        };
    }
    if PROGRAMS.contains(&program) {
        Ok(())
    } else {
        Err(format!(
            "{program}: not a command this test knows runs from a checkout (add it to PROGRAMS if it does)"
        ))
    }
}

/// Every command in a shell block, and every `$ ` line of a text block, is of a
/// runnable form.
#[test]
fn every_command_is_of_a_form_that_runs_from_a_checkout() {
    let mut cache = BTreeMap::new();
    let mut wrong = Vec::new();
    let mut seen = 0;
    for page in pages() {
        let md = std::fs::read_to_string(&page).unwrap();
        for b in blocks(&md) {
            let cmds: Vec<(String, String)> = match b.lang.as_str() {
                "sh" => commands(&b.text),
                "text" | "" | "console" => b
                    .text
                    .lines()
                    .filter_map(|l| l.strip_prefix("$ "))
                    .map(|c| (c.to_owned(), String::new()))
                    .collect(),
                _ => continue,
            };
            let installed = b.text.trim_start().starts_with(INSTALLED);
            for (cmd, _) in cmds {
                seen += 1;
                if let Err(why) = runnable(&cmd, installed, &mut cache) {
                    wrong.push(format!("{}:{}: `{cmd}`: {why}", name(&page), b.line));
                }
            }
        }
    }
    assert!(seen > 50, "only {seen} commands found");
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// Output as compared: numbers with a decimal point (times, rates) stand for any.
fn normalized(s: &str) -> String {
    let mut out = String::new();
    let chars: Vec<char> = s.trim_end().chars().collect();
    let mut i = 0;
    while i < chars.len() {
        if chars[i].is_ascii_digit() {
            let start = i;
            while i < chars.len() && chars[i].is_ascii_digit() {
                i += 1;
            }
            if i + 1 < chars.len() && chars[i] == '.' && chars[i + 1].is_ascii_digit() {
                i += 1;
                while i < chars.len() && chars[i].is_ascii_digit() {
                    i += 1;
                }
                out.push('#');
            } else {
                out.extend(&chars[start..i]);
            }
            continue;
        }
        out.push(chars[i]);
        i += 1;
    }
    out
}

/// The processes a block started with `&`: stopped (SIGTERM, then SIGKILL) when the
/// block is done, or when it failed.
struct Background(Vec<Child>);

impl Drop for Background {
    fn drop(&mut self) {
        for child in self.0.iter_mut().rev() {
            let _ = Command::new("kill")
                .args(["-TERM", &child.id().to_string()])
                .status();
            let end = Instant::now() + Duration::from_secs(5);
            while child.try_wait().ok().flatten().is_none() && Instant::now() < end {
                thread::sleep(Duration::from_millis(50));
            }
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// The examples share fixed ports: one block at a time.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

/// Runs the marked blocks of `page` (relative to the repository); the failures, each
/// with what was seen.
fn run_page(page: &str) -> Vec<String> {
    let _turn = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let md = std::fs::read_to_string(repo().join(page)).unwrap();
    let mut failures = Vec::new();
    let marked: Vec<Block> = blocks(&md).into_iter().filter(|b| b.run).collect();
    assert!(!marked.is_empty(), "{page}: no block marked <!-- run -->");
    for b in marked {
        assert_eq!(
            b.lang, "sh",
            "{page}:{}: a marked block is a sh block",
            b.line
        );
        let mut background = Background(Vec::new());
        // A person pastes the next line a moment after starting one in the background:
        // a simulator started before its pty exists needs that moment to find it.
        let mut started = false;
        let cmds = commands(&b.text);
        let last = cmds.len() - 1;
        for (i, (cmd, comment)) in cmds.iter().enumerate() {
            let line = cmd.replace("target/release/mbgate", BIN);
            let sh = |script: &str| {
                let mut c = Command::new("sh");
                c.args(["-c", script]).current_dir(repo());
                c
            };
            if let Some(cmd) = line.strip_suffix('&') {
                let child = sh(&format!("exec {cmd}"))
                    .stdin(Stdio::null())
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .spawn()
                    .unwrap();
                background.0.push(child);
                started = true;
                continue;
            }
            if std::mem::take(&mut started) {
                thread::sleep(Duration::from_secs(1));
            }
            let want_code = comment
                .split("exit code ")
                .nth(1)
                .and_then(|c| c.split(|ch: char| !ch.is_ascii_digit()).next())
                .and_then(|c| c.parse().ok())
                .unwrap_or(0);
            let want = (i == last).then_some(b.expected.as_deref()).flatten();
            // Again only while what the background started is not up yet: nothing
            // listens, or the gateway has not opened its port (0x0A), or a device a
            // busy machine runs late has not answered in time (0x0B, or no reply to
            // the client: a person runs it again too); any other answer is the
            // answer.
            let start = Instant::now();
            loop {
                let out = sh(&line).stdin(Stdio::null()).output().unwrap();
                let said = String::from_utf8_lossy(&out.stdout).into_owned()
                    + &String::from_utf8_lossy(&out.stderr);
                let code_ok = out.status.code() == Some(want_code);
                let output_ok = want.is_none_or(|w| normalized(&said) == normalized(w));
                if code_ok && output_ok {
                    break;
                }
                let not_up = said.contains("Connection refused")
                    || (said.contains("exception 0x0A")
                        && !want.is_some_and(|w| w.contains("0x0A")))
                    || (said.contains("exception 0x0B")
                        && !want.is_some_and(|w| w.contains("0x0B")))
                    || (said.contains("no reply from") && want_code == 0);
                if !not_up || start.elapsed() > Duration::from_secs(20) {
                    failures.push(format!(
                        "{page}:{}: `{cmd}` exited {:?} (want {want_code}) and said:\n{said}{}",
                        b.line,
                        out.status.code(),
                        want.map_or(String::new(), |w| format!("want:\n{w}"))
                    ));
                    break;
                }
                thread::sleep(Duration::from_millis(300));
            }
            if failures
                .last()
                .is_some_and(|f| f.contains(&format!(":{}:", b.line)))
            {
                break;
            }
        }
    }
    failures
}

fn assert_runs(page: &str) {
    let failures = run_page(page);
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}

#[test]
fn the_readme_runs_as_printed() {
    assert_runs("README.md");
}

#[test]
fn the_configuration_page_runs_as_printed() {
    assert_runs("docs/configuration.md");
}

#[test]
fn the_rtu_page_runs_as_printed() {
    assert_runs("docs/rtu-ascii.md");
}

#[test]
fn the_cie_m10_page_runs_as_printed() {
    assert_runs("docs/cie-m10.md");
}

#[test]
fn the_several_buses_page_runs_as_printed() {
    assert_runs("docs/several-buses.md");
}

#[test]
fn the_network_devices_page_runs_as_printed() {
    assert_runs("docs/network-devices.md");
}

#[test]
fn the_rtu_over_tcp_page_runs_as_printed() {
    assert_runs("docs/rtu-over-tcp.md");
}

#[test]
fn the_device_as_master_page_runs_as_printed() {
    assert_runs("docs/device-as-master.md");
}

#[test]
fn the_watching_page_runs_as_printed() {
    assert_runs("docs/watching.md");
}

#[test]
fn the_scan_page_runs_as_printed() {
    assert_runs("docs/scan.md");
}

#[test]
fn the_simulator_page_runs_as_printed() {
    assert_runs("docs/simulator.md");
}

#[test]
fn the_read_write_page_runs_as_printed() {
    assert_runs("docs/read-write.md");
}

/// Each marked page has its test above.
/// docs/security.md's openssl recipe, run as printed in a directory of its own instead
/// of /etc/mbgate/tls: the certificates it makes load in a TLS listener
/// (`check-config` reads every TLS file), and the master's carries its role.
#[test]
fn the_security_recipe_makes_certificates_the_gateway_takes() {
    let md = std::fs::read_to_string(repo().join("docs/security.md")).unwrap();
    let heading = md
        .find("### Making a CA and certificates with openssl")
        .expect("the recipe's heading");
    let block = blocks(&md[heading..])
        .into_iter()
        .find(|b| b.lang == "sh")
        .expect("the recipe");
    let first = "mkdir -p /etc/mbgate/tls && cd /etc/mbgate/tls";
    assert!(block.text.starts_with(first), "{}", block.text);
    let dir = common::tempdir();
    let script = block.text.replacen(first, "set -e", 1);
    let out = Command::new("bash")
        .arg("-c")
        .arg(&script)
        .current_dir(dir.path())
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{said}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The grep of the recipe shows the role.
    assert!(said.contains("operator"), "{said}");
    let cfg = dir.path().join("tls.toml");
    let d = dir.path().display();
    std::fs::write(
        &cfg,
        format!(
            "[[line]]\nserial = {{ path = \"/dev/ttyUSB0\" }}\n\n[[listen]]\naddress = \"127.0.0.1:802\"\n\
             tls = {{ cert = \"{d}/gateway.pem\", key = \"{d}/gateway.key\", client_ca = \"{d}/ca.pem\" }}\n\n\
             [[role]]\nname = \"operator\"\n"
        ),
    )
    .unwrap();
    let check = Command::new(BIN)
        .arg("check-config")
        .arg(&cfg)
        .output()
        .unwrap();
    assert!(
        check.status.success(),
        "{}{}",
        String::from_utf8_lossy(&check.stdout),
        String::from_utf8_lossy(&check.stderr)
    );
}

/// docs/security.md's walkthrough on this machine, run as printed but in a directory
/// and on a port of its own: the certificates, the configuration file, the pty pair,
/// simulator and gateway in the background, openssl's handshake and the pymodbus
/// master, each output compared with the text block the page shows after it.
#[test]
fn the_tls_walkthrough_runs_on_localhost_as_printed() {
    let md = std::fs::read_to_string(repo().join("docs/security.md")).unwrap();
    let from = md
        .find("### Trying it on this machine")
        .expect("the walkthrough");
    let to = md[from..].find("\n### ").map_or(md.len(), |n| from + n);
    let bs = blocks(&md[from..to]);
    let langs: Vec<&str> = bs.iter().map(|b| b.lang.as_str()).collect();
    assert_eq!(
        langs,
        ["sh", "toml", "sh", "text", "python", "text"],
        "the walkthrough's blocks"
    );
    let dir = common::tempdir();
    let port = common::free_port().to_string();
    let here = |t: &str| {
        t.replace("/tmp/mbgate-tls", dir.path().to_str().unwrap())
            .replace("8802", &port)
            .replace("target/release/mbgate", BIN)
    };
    let bash = |script: &str| {
        let out = Command::new("bash")
            .args(["-c", script])
            .current_dir(repo())
            .stdin(Stdio::null())
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        (
            out.status.success(),
            text,
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let (ok, out, err) = bash(&format!("set -e\n{}", here(&bs[0].text)));
    assert!(ok, "the certificates: {out}{err}");
    std::fs::write(dir.path().join("tls.toml"), here(&bs[1].text)).unwrap();
    let mut background = Background(Vec::new());
    let cmds = commands(&bs[2].text);
    let (last, starts) = cmds.split_last().unwrap();
    for (cmd, _) in starts {
        let cmd = here(cmd);
        let cmd = cmd.strip_suffix('&').expect("a background job");
        let child = Command::new("sh")
            .args(["-c", &format!("exec {cmd}")])
            .current_dir(repo())
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        background.0.push(child);
        // A person pastes the next line a moment later.
        thread::sleep(Duration::from_millis(500));
    }
    let addr: std::net::SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    common::wait_for("the gateway listening", Duration::from_secs(30), || {
        std::net::TcpStream::connect(addr).is_ok()
    });
    let (_, out, err) = bash(&here(&last.0));
    assert_eq!(out.trim(), bs[3].text.trim(), "openssl s_client: {err}");
    let py = Command::new(common::python())
        .arg("-c")
        .arg(here(&bs[4].text))
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        py.status.success(),
        "the pymodbus master: {}",
        String::from_utf8_lossy(&py.stderr)
    );
    assert_eq!(
        String::from_utf8_lossy(&py.stdout).trim(),
        bs[5].text.trim(),
        "the pymodbus master"
    );
}

#[test]
fn every_page_with_marked_blocks_is_run() {
    let tested = include_str!("docs.rs");
    for page in pages() {
        let md = std::fs::read_to_string(&page).unwrap();
        if blocks(&md).iter().any(|b| b.run) {
            let page = name(&page);
            assert!(
                tested.contains(&format!("assert_runs(\"{page}\")")),
                "{page} has blocks marked <!-- run --> and no test running them"
            );
        }
    }
}

/// GitHub's anchor for a heading: lower case, punctuation dropped, spaces as hyphens.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

/// The anchors of a page's headings (outside code blocks).
fn anchors(md: &str) -> BTreeSet<String> {
    let mut fenced = false;
    let mut out = BTreeSet::new();
    for line in md.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
        } else if !fenced && line.starts_with('#') {
            out.insert(slug(line.trim_start_matches('#')));
        }
    }
    out
}

/// The links of a page's text (outside code blocks and code spans).
fn links(md: &str) -> Vec<String> {
    let mut fenced = false;
    let mut out = Vec::new();
    for line in md.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        // Drop code spans.
        let text: String = line.split('`').step_by(2).collect::<Vec<_>>().join("");
        let mut rest = text.as_str();
        while let Some(at) = rest.find("](") {
            let tail = &rest[at + 2..];
            let Some(end) = tail.find(')') else { break };
            out.push(tail[..end].to_owned());
            rest = &tail[end..];
        }
    }
    out
}

#[test]
fn every_link_and_anchor_leads_somewhere() {
    let mut wrong = Vec::new();
    for page in pages() {
        let md = std::fs::read_to_string(&page).unwrap();
        for link in links(&md) {
            if link.starts_with("http://") || link.starts_with("https://") {
                continue;
            }
            let (path, anchor) = link.split_once('#').unwrap_or((&link, ""));
            let target = if path.is_empty() {
                page.clone()
            } else {
                page.parent().unwrap().join(path)
            };
            if !target.exists() {
                wrong.push(format!("{}: {link}: no such file", name(&page)));
                continue;
            }
            if !anchor.is_empty() {
                let text = std::fs::read_to_string(&target).unwrap_or_default();
                if !anchors(&text).contains(anchor) {
                    wrong.push(format!("{}: {link}: no such heading", name(&page)));
                }
            }
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// A section named in words rather than linked (`README "Some heading"`, `watching.md,
/// "Some heading"`) exists in that page.
#[test]
fn every_section_named_in_words_exists() {
    let mut wrong = Vec::new();
    let mut seen = 0;
    for page in pages() {
        let md = std::fs::read_to_string(&page).unwrap();
        let mut rest = md.as_str();
        while let Some(at) = rest.find(" \"") {
            let before = &rest[..at];
            let after = &rest[at + 2..];
            rest = &rest[at + 2..];
            let file = before
                .rsplit(|c: char| c.is_whitespace() || c == '(' || c == '`')
                .next()
                .unwrap_or("")
                .trim_end_matches(',');
            let target = match file {
                "README" | "README's" => repo().join("README.md"),
                f if f.ends_with(".md") && !f.contains('/') => page.parent().unwrap().join(f),
                _ => continue,
            };
            let Some(heading) = after.split('"').next() else {
                continue;
            };
            seen += 1;
            let text = std::fs::read_to_string(&target).unwrap_or_default();
            if !anchors(&text).contains(&slug(heading)) {
                wrong.push(format!(
                    "{}: {file} \"{heading}\": no such heading in {}",
                    name(&page),
                    name(&target)
                ));
            }
        }
    }
    assert!(wrong.is_empty(), "{} (of {seen})", wrong.join("\n"));
}

/// A count of the tests a page states (`about N tests`) is within a tenth of the
/// `#[test]` functions there are: it drifts as tests are added.
#[test]
fn every_count_of_tests_is_near_the_count() {
    fn count(dir: &Path) -> usize {
        let mut n = 0;
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                n += count(&p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                n += std::fs::read_to_string(&p)
                    .unwrap()
                    .matches("#[test]")
                    .count();
            }
        }
        n
    }
    let tests = count(&repo().join("src")) + count(&repo().join("tests"));
    for page in pages() {
        let md = std::fs::read_to_string(&page).unwrap();
        for (at, _) in md.match_indices(" tests") {
            let Some(said) = md[..at]
                .rsplit(|c: char| !c.is_ascii_digit())
                .next()
                .and_then(|n| n.parse::<usize>().ok())
            else {
                continue;
            };
            if !md[..at]
                .trim_end_matches(char::is_numeric)
                .ends_with("about ")
            {
                continue;
            }
            assert!(
                said * 10 >= tests * 9 && said * 10 <= tests * 11,
                "{}: \"about {said} tests\", and there are {tests}",
                name(&page)
            );
        }
    }
}

/// What the docs say of the status page's frame list holds: it shows as many frames
/// as the gateway keeps (src/ops/capture/hub.rs, `RECENT`).
#[test]
fn the_status_page_frames_the_docs_state_are_the_ones_kept() {
    let hub = std::fs::read_to_string(repo().join("src/ops/capture/hub.rs")).unwrap();
    let kept: usize = hub
        .split("pub(crate) const RECENT: usize = ")
        .nth(1)
        .and_then(|r| r.split(';').next())
        .and_then(|n| n.parse().ok())
        .expect("RECENT in src/ops/capture/hub.rs");
    let mut seen = 0;
    for page in pages() {
        let md = std::fs::read_to_string(&page).unwrap().replace('\n', " ");
        for (at, _) in md.match_indices(" frames") {
            let before = md[..at].trim_end();
            let Some(n) = before
                .rsplit(|c: char| !c.is_ascii_digit())
                .next()
                .and_then(|n| n.parse::<usize>().ok())
            else {
                continue;
            };
            let lead = before.trim_end_matches(char::is_numeric).trim_end();
            if lead.ends_with("last") || lead.ends_with("Last") {
                seen += 1;
                assert_eq!(n, kept, "{}: \"last {n} frames\"", name(&page));
            }
        }
    }
    assert!(seen >= 2, "only {seen} mentions of the last frames");
}

/// The example configurations: each valid (OK, nothing to warn about), each named in
/// the README or the guide, and a copy of one in the guide is the file.
#[test]
fn every_example_configuration_is_valid_named_and_copied_faithfully() {
    let all: String = pages()
        .iter()
        .map(|p| std::fs::read_to_string(p).unwrap())
        .collect();
    let mut examples: Vec<PathBuf> = std::fs::read_dir(repo().join("config/examples"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    examples.sort();
    assert!(examples.len() >= 7, "{examples:?}");
    for file in &examples {
        let base = file.file_name().unwrap().to_str().unwrap();
        let out = Command::new(BIN)
            .args(["check-config", file.to_str().unwrap()])
            .output()
            .unwrap();
        let (stdout, stderr) = (
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr),
        );
        assert!(
            out.status.success() && stdout.starts_with("OK: ") && stderr.is_empty(),
            "{base}: {stdout}{stderr}"
        );
        assert!(
            all.contains(&format!("config/examples/{base}")),
            "{base} is named nowhere in the README or docs/"
        );
        let text = std::fs::read_to_string(file).unwrap();
        let first = text.lines().next().unwrap();
        for page in pages() {
            let md = std::fs::read_to_string(&page).unwrap();
            for b in blocks(&md).iter().filter(|b| b.lang == "toml") {
                if b.text.lines().next() == Some(first) {
                    assert_eq!(b.text, text, "{}:{}: a copy of {base}", name(&page), b.line);
                }
            }
        }
    }
}

/// packaging/ holds what `mbgate generate` writes now: the man pages and the bash, zsh
/// and fish completions (scripts/generate writes them).
#[test]
fn the_man_pages_and_completions_are_generated_from_this_command_line() {
    let dir = common::tempdir();
    let out = Command::new(BIN)
        .args(["generate", "man", dir.path().to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    let listing = |d: &Path| -> BTreeSet<String> {
        std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect()
    };
    let shipped = repo().join("packaging/man");
    let stale = "packaging/ is not what this binary generates: run scripts/generate and commit";
    assert_eq!(listing(dir.path()), listing(&shipped), "{stale}");
    for page in listing(&shipped) {
        let now = std::fs::read_to_string(dir.path().join(&page)).unwrap();
        let kept = std::fs::read_to_string(shipped.join(&page)).unwrap();
        assert!(now == kept, "{page}: {stale}");
    }
    for (shell, file) in [
        ("bash", "mbgate.bash"),
        ("zsh", "_mbgate"),
        ("fish", "mbgate.fish"),
    ] {
        let out = Command::new(BIN)
            .args(["generate", "completions", shell])
            .output()
            .unwrap();
        let kept = std::fs::read(repo().join("packaging/completions").join(file)).unwrap();
        assert!(out.stdout == kept, "{file}: {stale}");
    }
}

/// Whether `program` runs here; when it does not, the test skips (common::peer).
fn have(program: &str) -> bool {
    let package = match program {
        "man" => "man-db",
        other => other,
    };
    peer(program, package)
}

/// mbgate.toml(5), as man renders it, keeps each line of config/mbgate.toml's
/// commented-out examples that is itself a comment (`# # ...`) a line of its own, so
/// that an example pasted from the page is still TOML; mbgate(1)'s exit codes end
/// before the sentence after them.
#[test]
fn the_man_pages_keep_examples_verbatim_and_sentences_apart() {
    if !have("man") {
        return;
    }
    let render = |page: &str| {
        let out = Command::new("man")
            .args(["-l"])
            .arg(repo().join("packaging/man").join(page))
            .env("MANWIDTH", "200")
            .env("MANPAGER", "cat")
            .output()
            .unwrap();
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    let page = render("mbgate.toml.5");
    let shown: Vec<&str> = page.lines().map(str::trim).collect();
    let file = std::fs::read_to_string(repo().join("config/mbgate.toml")).unwrap();
    let mut seen = 0;
    for line in file.lines() {
        let Some(inner) = line.strip_prefix("# # ") else {
            continue;
        };
        seen += 1;
        let want = format!("# {inner}");
        assert!(
            shown.iter().any(|l| *l == want.trim()),
            "mbgate.toml(5) does not show `{want}` as a line of its own"
        );
    }
    assert!(seen >= 5, "only {seen} commented comment lines");
    let top = render("mbgate.1");
    let lines: Vec<&str> = top.lines().collect();
    let at = lines
        .iter()
        .position(|l| l.contains("The subcommands read, write and status"))
        .unwrap_or_else(|| panic!("{top}"));
    assert!(
        lines[at].trim().starts_with("The subcommands") && lines[at - 1].trim().is_empty(),
        "mbgate(1): the exit codes run into the next sentence:\n{}\n{}",
        lines[at - 1],
        lines[at]
    );
}

/// Each page renders with man(1) without a warning, with its title and a NAME section.
#[test]
fn the_man_pages_render_without_a_warning() {
    if !have("man") {
        return;
    }
    let dir = repo().join("packaging/man");
    for page in std::fs::read_dir(&dir).unwrap() {
        let page = page.unwrap().path();
        let out = Command::new("man")
            .args(["--warnings", "-l"])
            .arg(&page)
            .env("MANWIDTH", "80")
            .env("MANPAGER", "cat")
            .output()
            .unwrap();
        let (text, warned) = (
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr),
        );
        let file = page.file_name().unwrap().to_str().unwrap();
        let (title, section) = file.rsplit_once('.').unwrap();
        let head = format!("{}({section})", title.to_uppercase());
        assert!(
            out.status.success() && warned.is_empty(),
            "{file}: {warned}"
        );
        assert!(
            text.starts_with(&head),
            "{file}: {}",
            &text[..text.len().min(200)]
        );
        assert!(text.contains("\nNAME\n"), "{file}");
    }
}

/// Each shell loads its completion script: bash registers it for mbgate and completes
/// a subcommand; zsh and fish parse it.
#[test]
fn each_shell_loads_its_completions() {
    let dir = repo().join("packaging/completions");
    let bash = format!(
        "source {}; complete -p mbgate >/dev/null && COMP_WORDS=(mbgate check-co) COMP_CWORD=1 \
         && _mbgate mbgate check-co mbgate && echo \"${{COMPREPLY[@]}}\"",
        dir.join("mbgate.bash").display()
    );
    let out = Command::new("bash").args(["-c", &bash]).output().unwrap();
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).trim(),
        "check-config",
        "{out:?}"
    );
    for (shell, args, file) in [
        ("zsh", &["-n"][..], "_mbgate"),
        ("fish", &["--no-execute"][..], "mbgate.fish"),
    ] {
        if !have(shell) {
            continue;
        }
        let out = Command::new(shell)
            .args(args)
            .arg(dir.join(file))
            .output()
            .unwrap();
        assert!(out.status.success(), "{shell}: {out:?}");
    }
}
