//! The map held to the code: every file, folder, module path and type that
//! docs/architecture.md and CONTRIBUTING.md name exists in the tree, so a rename or a
//! move that forgets the docs fails here, naming what is missing.

use super::repo;
use std::path::{Path, PathBuf};

/// The pages that describe the code.
const PAGES: &[&str] = &["docs/architecture.md", "CONTRIBUTING.md"];
/// The folders at the top of the checkout a named path may start with.
const ROOTS: &[&str] = &[
    "src/",
    "tests/",
    "benches/",
    "fuzz/",
    "scripts/",
    "docs/",
    "packaging/",
    "systemd/",
    "config/",
    ".ci/",
    ".cargo/",
];
/// Where a file named by its tail alone (`mbap/tests.rs`, `kind.rs` tests) is looked
/// for.
const CODE: &[&str] = &["src", "tests", "benches", "fuzz"];

/// Every file under `dir`, as paths from the checkout, folders with a trailing `/`.
fn tree(dir: &Path, out: &mut Vec<String>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let path = e.unwrap().path();
        let rel = path.strip_prefix(repo()).unwrap().display().to_string();
        if path.is_dir() {
            out.push(format!("{rel}/"));
            tree(&path, out);
        } else {
            out.push(rel);
        }
    }
}

/// The text of `md` outside fenced blocks, and the fenced blocks' text.
fn prose_and_fences(md: &str) -> (String, String) {
    let (mut prose, mut fences) = (String::new(), String::new());
    let mut fenced = false;
    for line in md.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        let to = if fenced { &mut fences } else { &mut prose };
        to.push_str(line);
        to.push('\n');
    }
    (prose, fences)
}

/// The inline code spans of `prose`.
fn spans(prose: &str) -> Vec<String> {
    prose
        .split('`')
        .skip(1)
        .step_by(2)
        .map(|s| s.split_whitespace().collect::<Vec<_>>().join(" "))
        .collect()
}

fn is_path_char(c: char) -> bool {
    c.is_ascii_alphanumeric() || "_./-".contains(c)
}

/// Does `name` (a path from the checkout, or the tail of one) name a file or folder?
fn found(name: &str, files: &[String]) -> bool {
    let bare = name.trim_end_matches('/');
    let root = repo();
    if root.join(bare).exists() || root.join("src").join(bare).exists() {
        return true;
    }
    // A fuzz target by its name (`fuzz/pdu`).
    if let Some(target) = bare.strip_prefix("fuzz/") {
        if root.join(format!("fuzz/fuzz_targets/{target}.rs")).exists() {
            return true;
        }
    }
    if ROOTS.iter().any(|r| name.starts_with(r)) {
        return false;
    }
    files.iter().any(|f| {
        let f = f.trim_end_matches('/');
        CODE.iter().any(|c| f.starts_with(&format!("{c}/"))) && f.ends_with(&format!("/{bare}"))
    })
}

/// The paths `text` names: every `src/...`, and in `spans_only` tokens that end in
/// `.rs` or `/`, or start at a folder of the checkout.
fn paths(text: &str, tokens: &[String]) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(at) = rest.find("src/") {
        let before = rest[..at].chars().next_back();
        let tail: String = rest[at..]
            .chars()
            .take_while(|&c| is_path_char(c))
            .collect();
        rest = &rest[at + 4..];
        if before.is_some_and(|c| is_path_char(c) || c == '/') {
            continue;
        }
        out.push(tail.trim_end_matches(['.', ',']).to_string());
    }
    for t in tokens {
        let t = t
            .trim_end_matches([',', ':', ';', ')'])
            .trim_start_matches('(');
        if t.is_empty()
            || !t.chars().all(is_path_char)
            || t.starts_with('/')
            || t.starts_with("..")
            || t.contains("//")
        {
            continue;
        }
        let file_like = t.ends_with(".rs") || (t.ends_with('/') && t.len() > 1);
        if file_like || ROOTS.iter().any(|r| t.starts_with(r)) {
            out.push(t.to_string());
        }
    }
    out
}

/// The non-comment lines of a Rust file.
fn code_of(path: &Path) -> String {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .filter(|l| {
            let t = l.trim_start();
            !(t.starts_with("//") || t.starts_with("#["))
        })
        .collect::<Vec<_>>()
        .join("\n")
}

fn has_word(text: &str, word: &str) -> bool {
    let ident = |c: char| c.is_ascii_alphanumeric() || c == '_';
    text.match_indices(word).any(|(i, _)| {
        !text[..i].chars().next_back().is_some_and(ident)
            && !text[i + word.len()..].chars().next().is_some_and(ident)
    })
}

/// Does the module whose code is `code` declare `item`, or bring it in with `use`?
fn declares(code: &str, item: &str) -> bool {
    const KEYWORDS: &[&str] = &[
        "fn", "struct", "enum", "trait", "type", "const", "static", "mod", "union",
    ];
    if KEYWORDS
        .iter()
        .any(|k| has_word(code, &format!("{k} {item}")))
        || has_word(code, &format!("macro_rules! {item}"))
        || has_word(code, &format!("impl {item}"))
        // An enum a declaring macro makes (`Framing { Mbap = "mbap", ... }`).
        || code.lines().any(|l| l.trim() == format!("{item} {{"))
    {
        return true;
    }
    // `use a::{b, item}`, over several lines.
    let mut rest = code;
    while let Some(at) = rest.find("use ") {
        let stmt = &rest[at..rest[at..].find(';').map_or(rest.len(), |e| at + e)];
        if has_word(stmt, item) {
            return true;
        }
        rest = &rest[at + 4..];
    }
    false
}

/// The files of module `segments` (`["relay", "line"]`): `src/relay/line.rs` or
/// `src/relay/line/mod.rs`.
fn module_file(segments: &[&str]) -> Option<PathBuf> {
    let base = repo().join("src").join(segments.join("/"));
    [base.with_extension("rs"), base.join("mod.rs")]
        .into_iter()
        .find(|p| p.is_file())
}

/// Why the module path `path` (`relay::inflight::InFlight`, `frame::pdu::check_request`)
/// leads nowhere, if it does; `None` also when its first step is no room of the crate
/// (`Framing::framer`: a type's own, checked with its type where a row names it).
fn lost(path: &str, all_code: &str) -> Option<String> {
    let path = path.trim_end_matches("()");
    let segments: Vec<&str> = path
        .strip_prefix("crate::")
        .unwrap_or(path)
        .split("::")
        .collect();
    let first = segments[0];
    if !first.chars().all(|c| c.is_ascii_lowercase() || c == '_')
        || matches!(first, "lib" | "main")
        || module_file(&[first]).is_none()
    {
        return None;
    }
    let mut depth = 1;
    while depth < segments.len() && module_file(&segments[..=depth]).is_some() {
        depth += 1;
    }
    let module = module_file(&segments[..depth]).unwrap();
    // A module alone is found.
    let item = segments.get(depth)?;
    if !declares(&code_of(&module), item) {
        return Some(format!(
            "`{path}`: {} declares no `{item}`",
            module.strip_prefix(repo()).unwrap().display()
        ));
    }
    // What follows the item (a method, a variant) is somewhere in the code.
    for more in &segments[depth + 1..] {
        if !has_word(all_code, more) {
            return Some(format!("`{path}`: no `{more}` in src/"));
        }
    }
    None
}

/// In a table row whose first cell names files of `src/`, every type or constant the
/// row names in backticks is in one of those files.
fn row_types(row: &str, files: &[String]) -> Vec<String> {
    let cells: Vec<&str> = row.trim().trim_matches('|').split(" | ").collect();
    let Some((first, rest)) = cells.split_first() else {
        return Vec::new();
    };
    let named: Vec<String> = spans(first)
        .into_iter()
        .filter(|s| s.starts_with("src/") && files.iter().any(|f| f == s))
        .collect();
    let sources: Vec<String> = named
        .iter()
        .filter(|f| f.ends_with(".rs"))
        .map(|f| code_of(&repo().join(f)))
        .collect();
    if sources.is_empty() {
        return Vec::new();
    }
    let mut wrong = Vec::new();
    for s in spans(&rest.join(" | ")) {
        let is_type = s.starts_with(|c: char| c.is_ascii_uppercase())
            && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
            && s.chars().any(|c| c.is_ascii_lowercase() || c == '_');
        if is_type && !sources.iter().any(|code| has_word(code, &s)) {
            wrong.push(format!("`{s}`: not in {}", named.join(", ")));
        }
    }
    wrong
}

/// docs/architecture.md and CONTRIBUTING.md name only what the tree has: every path of
/// `src/` (and every `.rs` file or folder named by its tail, as the request's path
/// does), every module path whose first step is a room of the crate
/// (`relay::inflight::InFlight`: the module, then its item), and every type a file's
/// row of a table names, in that file.
#[test]
fn the_map_names_only_what_the_code_has() {
    let mut files = Vec::new();
    tree(&repo().join("src"), &mut files);
    for dir in ["tests", "benches", "fuzz/fuzz_targets"] {
        tree(&repo().join(dir), &mut files);
    }
    let all_code: String = files
        .iter()
        .filter(|f| f.starts_with("src/") && f.ends_with(".rs"))
        .map(|f| code_of(&repo().join(f)))
        .collect::<Vec<_>>()
        .join("\n");
    let mut wrong = Vec::new();
    let mut checked = 0;
    for page in PAGES {
        let md = std::fs::read_to_string(repo().join(page)).unwrap();
        let (prose, fences) = prose_and_fences(&md);
        let spans = spans(&prose);
        let words: Vec<String> = fences
            .split(|c: char| c.is_whitespace() || "(),;:".contains(c))
            .map(str::to_string)
            .collect();
        let mut named = paths(&prose, &spans);
        named.extend(paths(&fences, &words));
        named.sort();
        named.dedup();
        for p in &named {
            checked += 1;
            if !found(p, &files) {
                wrong.push(format!("{page}: `{p}`: no such file or folder"));
            }
        }
        for s in &spans {
            if s.contains("::")
                && s.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "_:()".contains(c))
            {
                checked += 1;
                if let Some(why) = lost(s, &all_code) {
                    wrong.push(format!("{page}: {why}"));
                }
            }
        }
        for row in prose.lines().filter(|l| l.starts_with("| `src/")) {
            checked += 1;
            wrong.extend(
                row_types(row, &files)
                    .into_iter()
                    .map(|w| format!("{page}: {w}")),
            );
        }
    }
    assert!(
        checked > 200,
        "only {checked} names found: is the parsing right?"
    );
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}
