//! docs/architecture.md "House rules" on the public surface, held to src/: an item is
//! `pub` only if a user outside the library names it (the binary, tests/, benches/,
//! the fuzz targets, a doc example) or a public item's interface does; the rest is
//! `pub(crate)`. `unreachable_pub` (Cargo.toml `[lints]`) holds the rooms that are not
//! public; this holds the ones that are.

use super::map::{production, tree};
use super::repo;

/// The words of `text`: its runs of letters, digits and `_`.
fn words(text: &str) -> std::collections::BTreeSet<&str> {
    text.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .filter(|w| !w.is_empty())
        .collect()
}

/// The doc examples of a file (the code blocks of its `///` and `//!` comments that
/// rustdoc runs): users outside the library too.
fn doc_examples(text: &str) -> String {
    let mut out = String::new();
    let mut inside = false;
    for line in text.lines() {
        let t = line.trim_start();
        let Some(doc) = t.strip_prefix("///").or_else(|| t.strip_prefix("//!")) else {
            inside = false;
            continue;
        };
        let doc = doc.strip_prefix(' ').unwrap_or(doc);
        if let Some(lang) = doc.strip_prefix("```") {
            inside = !inside && matches!(lang.trim(), "" | "rust");
        } else if inside {
            out.push_str(doc);
            out.push('\n');
        }
    }
    out
}

/// The code of every user outside the library.
fn outside() -> String {
    let mut files = vec!["src/main.rs".to_string()];
    for dir in ["tests", "benches", "fuzz/fuzz_targets"] {
        tree(&repo().join(dir), &mut files);
    }
    let mut out = String::new();
    for file in files.iter().filter(|f| f.ends_with(".rs")) {
        // This file names no item of the library.
        if file != "tests/packaging/docs/surface.rs" {
            out.push_str(&std::fs::read_to_string(repo().join(file)).unwrap());
        }
    }
    out
}

/// The identifier `s` begins with.
fn word(s: &str) -> Option<&str> {
    s.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .next()
}

/// The name a line declares public, if it is one: `pub fn name`, `pub struct Name`,
/// `pub name: Type` (a field), or the names of `pub use path::{A, b}` (one line).
fn declared(line: &str) -> Vec<&str> {
    let Some(rest) = line.trim_start().strip_prefix("pub ") else {
        return Vec::new();
    };
    if let Some(tree) = rest.strip_prefix("use ") {
        let names = tree.rsplit([':', '{']).next().unwrap_or("");
        return match tree.split_once('{') {
            Some((_, group)) => group.split([',', '}', ';']).map(str::trim).collect(),
            None => vec![names.trim_end_matches(';')],
        }
        .into_iter()
        .filter(|n| !n.is_empty())
        .collect();
    }
    let mut rest = rest;
    for qualifier in ["async ", "const ", "unsafe ", "extern \"C\" "] {
        rest = rest.strip_prefix(qualifier).unwrap_or(rest);
    }
    let kinds = [
        "fn ", "struct ", "enum ", "trait ", "type ", "const ", "static ", "mod ", "union ",
    ];
    match kinds.iter().find_map(|k| rest.strip_prefix(k)) {
        Some(named) => word(named).into_iter().collect(),
        None if rest.contains(':') => word(rest).into_iter().collect(),
        None => Vec::new(),
    }
}

/// The public interface as text: every `pub` line (a signature to its `{` or `;`), the
/// bodies of `pub enum`s and `pub trait`s (variants, methods), the tables the config
/// macros make `pub` structs of, and a crate-private type alias such an interface
/// names (what it stands for).
fn interface(files: &[(String, String)]) -> String {
    let mut out = String::new();
    let mut aliases = Vec::new();
    for (_, code) in files {
        let lines: Vec<&str> = code.lines().collect();
        let mut i = 0;
        while i < lines.len() {
            let line = lines[i];
            let t = line.trim_start();
            let indent = line.len() - t.len();
            let opens_public_body = t.starts_with("pub enum ") || t.starts_with("pub trait ");
            let macro_table = ["table! {", "settings! {", "choices! {"].contains(&t);
            if t.starts_with("pub(crate) type ") {
                aliases.push(t);
            }
            if !(t.starts_with("pub ") || macro_table) {
                i += 1;
                continue;
            }
            // The signature, up to its body or its end.
            let ends: &[char] = if t.contains("fn ") {
                &['{', ';']
            } else {
                &['{', ';', ',']
            };
            let mut j = i;
            while j + 1 < lines.len() && !lines[j].trim_end().ends_with(ends) {
                j += 1;
            }
            if opens_public_body || macro_table {
                while j + 1 < lines.len()
                    && !(lines[j + 1].len() - lines[j + 1].trim_start().len() == indent
                        && lines[j + 1].trim_start().starts_with('}'))
                {
                    j += 1;
                }
            }
            for l in &lines[i..=j] {
                out.push_str(l);
                out.push('\n');
            }
            i = j + 1;
        }
    }
    let named = words(&out)
        .into_iter()
        .map(str::to_string)
        .collect::<Vec<_>>();
    for alias in aliases {
        let public = alias.replacen("pub(crate) ", "pub ", 1);
        let name = declared(&public);
        if name.iter().any(|n| named.iter().any(|w| w == n)) {
            out.push_str(alias);
            out.push('\n');
        }
    }
    out
}

/// Every `pub` item, field and re-export of src/ is named outside the library or by a
/// public interface; anything else is `pub(crate)` (or narrower), so that `pub` says
/// "public" and `unreachable_pub` and `dead_code` see the rest.
#[test]
fn what_is_pub_is_used_outside_the_library() {
    let mut paths = Vec::new();
    tree(&repo().join("src"), &mut paths);
    let mut files = Vec::new();
    let mut outside = outside();
    for path in paths
        .iter()
        .filter(|p| p.ends_with(".rs") && !p.ends_with("/tests.rs"))
    {
        let text = std::fs::read_to_string(repo().join(path)).unwrap();
        outside.push_str(&doc_examples(&text));
        files.push((path.clone(), production(&repo().join(path))));
    }
    let outside = words(&outside);
    let interface = interface(&files);
    let mut unused = Vec::new();
    for (path, code) in &files {
        for (n, line) in code.lines().enumerate() {
            // A macro's `pub $field` is its invocations' business (held where they are).
            if line.contains('$') {
                continue;
            }
            for name in declared(line) {
                // Named outside, or in a public interface beside its own declaration.
                let in_interface = interface
                    .lines()
                    .filter(|l| !declared(l).contains(&name))
                    .any(|l| words(l).contains(name));
                if !outside.contains(name) && !in_interface {
                    unused.push(format!("{path}:{}: `{name}`", n + 1));
                }
            }
        }
    }
    assert!(
        unused.is_empty(),
        "`pub` but named by no user outside the library (src/main.rs, tests/, benches/, \
         fuzz/, a doc example) nor by a public interface; make it pub(crate):\n{}",
        unused.join("\n")
    );
}
