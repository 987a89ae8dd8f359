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
pub(super) fn tree(dir: &Path, out: &mut Vec<String>) {
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

/// The paths `text` names: every `src/...`, and among `tokens` those that end in
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

/// The files of module `segments` (`["relay", "line"]`): `src/line/relay/line.rs` or
/// `src/line/relay/line/mod.rs`.
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

/// The files of `src/` a table row of `page` names: its first cell's paths, and every
/// `.rs` or `.html` file another cell names from the row's folder (`mbap/tests.rs` in
/// the row of `src/line/relay/line/mbap/mod.rs`, `console.rs` in the row of `src/tools/sim/`).
fn rows_name(page: &str) -> Vec<String> {
    let mut named = Vec::new();
    for row in page.lines().filter(|l| l.starts_with("| `src/")) {
        let first = row
            .trim_start_matches('|')
            .split(" | ")
            .next()
            .unwrap_or("");
        let bases: Vec<String> = spans(first)
            .into_iter()
            .filter(|s| s.starts_with("src/"))
            .map(|p| match p.ends_with('/') {
                true => p,
                false => p[..=p.rfind('/').unwrap()].to_string(),
            })
            .collect();
        for s in spans(row) {
            named.push(s.clone());
            if s.ends_with(".rs") || s.ends_with(".html") {
                named.extend(bases.iter().map(|b| format!("{b}{s}")));
            }
        }
    }
    named
}

/// docs/architecture.md is the map of every file: each source file of `src/` is named
/// there, by its path or in its folder's row.
#[test]
fn every_source_file_is_on_the_map() {
    let mut files = Vec::new();
    tree(&repo().join("src"), &mut files);
    let page = std::fs::read_to_string(repo().join("docs/architecture.md")).unwrap();
    let mut named = rows_name(&page);
    named.extend(paths(&page, &[]));
    let missing: Vec<&String> = files
        .iter()
        .filter(|f| f.ends_with(".rs") || f.ends_with(".html"))
        .filter(|f| !named.contains(f))
        // A folder module's tests sit in `tests.rs` beside its `mod.rs` (the
        // convention of "The wings"): its module's row names them.
        .filter(|f| {
            let module = f.strip_suffix("/tests.rs").map(|m| format!("{m}/mod.rs"));
            !module
                .is_some_and(|m| named.contains(&m) || named.contains(&m.replace("/mod.rs", "/")))
        })
        .collect();
    assert!(
        missing.is_empty(),
        "files of src/ docs/architecture.md does not name: {missing:?}"
    );
}

/// The wings of `src/`: folders that hold rooms and nothing else (docs/architecture.md
/// "The rooms"). A room in a wing is named by both steps (`line/relay`).
const WINGS: &[&str] = &["masters", "line", "ops", "tools"];

/// The room of a source file: its first step under `src/` (`config` for
/// `src/config/file/mod.rs`), or its first two when the first is a wing
/// (`line/relay` for `src/line/relay/line/mod.rs`).
fn room(file: &str) -> String {
    room_of_path(&file["src/".len()..].replace('/', "::"))
}

/// The room a Rust path names after `crate::` (`line::relay::Relay` → `line/relay`).
fn room_of_path(path: &str) -> String {
    let steps: Vec<String> = path
        .split("::")
        .map(|s| {
            s.chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect()
        })
        .take(2)
        .collect();
    match steps.as_slice() {
        [wing, room] if WINGS.contains(&wing.as_str()) && !room.is_empty() => {
            format!("{wing}/{room}")
        }
        [first, ..] => first.clone(),
        [] => String::new(),
    }
}

/// A wing holds rooms and nothing else: its `mod.rs` is its doc and the rooms it
/// declares, so a room's code never sits between the rooms.
#[test]
fn a_wing_holds_only_rooms() {
    for wing in WINGS {
        let code = production(&repo().join(format!("src/{wing}/mod.rs")));
        for line in code.lines().map(str::trim).filter(|l| !l.is_empty()) {
            let decl = line
                .trim_start_matches("pub(crate) ")
                .trim_start_matches("pub ");
            assert!(
                decl.starts_with("mod ") && decl.ends_with(';'),
                "src/{wing}/mod.rs: `{line}` is not a room's declaration"
            );
        }
    }
}

/// The production code of a source file: no comments, no test module.
pub(super) fn production(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap();
    let mut out = String::new();
    let mut lines = text.lines().peekable();
    while let Some(line) = lines.next() {
        let t = line.trim_start();
        if t == "#[cfg(test)]"
            && lines
                .peek()
                .is_some_and(|n| n.trim_start().starts_with("mod "))
        {
            break;
        }
        out.push_str(line.split("//").next().unwrap());
        out.push('\n');
    }
    out
}

/// The rooms' drawing of docs/architecture.md, "The rooms", holds: a room's
/// production code names (`crate::room`, or `mbgate::room` in main.rs) only rooms in
/// rows below it, or to its right in its own row; and every room is drawn.
#[test]
fn every_import_points_down_the_rooms_drawing() {
    let page = std::fs::read_to_string(repo().join("docs/architecture.md")).unwrap();
    let after = &page[page.find("## The rooms").expect("the rooms section")..];
    let start = after.find("```").unwrap() + 3;
    let drawing = &after[start..start + after[start..].find("```").unwrap()];
    // (row, place in the row) of each room drawn.
    let mut place = std::collections::BTreeMap::new();
    let mut row = 0;
    for line in drawing.lines() {
        let rooms: Vec<String> = line
            .split_whitespace()
            .filter(|w| {
                (w.ends_with(".rs") || w.ends_with('/'))
                    && w.chars()
                        .all(|c| c.is_ascii_lowercase() || "_./".contains(c))
            })
            .map(|w| w.trim_end_matches('/').trim_end_matches(".rs").to_string())
            .collect();
        if rooms.is_empty() {
            continue;
        }
        for (i, r) in rooms.into_iter().enumerate() {
            place.insert(r, (row, i));
        }
        row += 1;
    }
    let mut files = Vec::new();
    tree(&repo().join("src"), &mut files);
    let mut wrong = Vec::new();
    for file in files.iter().filter(|f| f.ends_with(".rs")) {
        let from = room(file);
        let wing_index = WINGS.iter().any(|w| *file == format!("src/{w}/mod.rs"));
        if from == "lib" || wing_index || file.ends_with("/tests.rs") || file.contains("/tests/") {
            continue;
        }
        let Some(&at) = place.get(&from) else {
            wrong.push(format!("{file}: room `{from}` is not drawn"));
            continue;
        };
        let code = production(&repo().join(file));
        let mut seen = std::collections::BTreeSet::new();
        for prefix in ["crate::", "mbgate::"] {
            for (i, _) in code.match_indices(prefix) {
                let to = room_of_path(&code[i + prefix.len()..]);
                if to == from || !seen.insert(to.clone()) {
                    continue;
                }
                if let Some(&there) = place.get(&to) {
                    if there <= at {
                        wrong.push(format!(
                            "{file}: `{from}` uses `{to}`, above it or to its left"
                        ));
                    }
                }
            }
        }
    }
    assert!(
        place.len() > 20,
        "only {} rooms drawn: is the parsing right?",
        place.len()
    );
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// The wings are layers (docs/architecture.md "The wings", its line "The order, top to
/// bottom: ..."): the production code of each first-level entry of `src/` names
/// (`crate::x`, or `mbgate::x` in main.rs) only entries below it in that order; every
/// entry is in the order, and the order names only entries there are.
#[test]
fn every_wing_imports_only_the_wings_below_it() {
    let page = std::fs::read_to_string(repo().join("docs/architecture.md")).unwrap();
    let after = &page[page.find("## The wings").expect("the wings section")..];
    let line = &after[after.find("The order, top to bottom:").expect("the order")..];
    let line = &line[..line.find(".\n").expect("the order's end")];
    let order: Vec<String> = line
        .split('`')
        .skip(1)
        .step_by(2)
        .map(str::to_string)
        .collect();
    let mut files = Vec::new();
    tree(&repo().join("src"), &mut files);
    let entry = |file: &str| -> String {
        let first = file["src/".len()..].split('/').next().unwrap();
        match first.trim_end_matches(".rs") {
            "main" => "cli".to_string(),
            other => other.to_string(),
        }
    };
    let mut wrong = Vec::new();
    let mut seen = std::collections::BTreeSet::new();
    for file in files.iter().filter(|f| f.ends_with(".rs")) {
        let from = entry(file);
        if from == "lib" || file.ends_with("/tests.rs") || file.contains("/tests/") {
            continue;
        }
        seen.insert(from.clone());
        let Some(at) = order.iter().position(|w| *w == from) else {
            wrong.push(format!("{file}: `{from}` is not in the order"));
            continue;
        };
        let code = production(&repo().join(file));
        let mut named = std::collections::BTreeSet::new();
        for prefix in ["crate::", "mbgate::"] {
            for (i, _) in code.match_indices(prefix) {
                let to: String = code[i + prefix.len()..]
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect();
                if to == from || !named.insert(to.clone()) {
                    continue;
                }
                match order.iter().position(|w| *w == to) {
                    Some(there) if there < at => {
                        wrong.push(format!("{file}: `{from}` uses `{to}`, a wing above it"))
                    }
                    _ => {}
                }
            }
        }
    }
    for w in &order {
        if !seen.contains(w) {
            wrong.push(format!("the order names `{w}`, which src/ does not have"));
        }
    }
    assert!(order.len() >= 8, "only {order:?}: is the parsing right?");
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// The number of files in `src/` a new framing touches, as the pages state it
/// ("13 in `src/` today"), is the number that name `Framing::Ascii`,
/// `SerialFraming::Ascii` (the scan's) or `Codec::Ascii`.
#[test]
fn the_files_a_framing_touches_are_counted_right() {
    let mut files = Vec::new();
    tree(&repo().join("src"), &mut files);
    let count = files
        .iter()
        .filter(|f| f.ends_with(".rs"))
        .filter(|f| {
            let text = std::fs::read_to_string(repo().join(f)).unwrap();
            ["Framing::Ascii", "SerialFraming::Ascii", "Codec::Ascii"]
                .iter()
                .any(|w| has_word(&text, w))
        })
        .count();
    let mut stated = Vec::new();
    for page in PAGES {
        let md = std::fs::read_to_string(repo().join(page)).unwrap();
        let md = md.split_whitespace().collect::<Vec<_>>().join(" ");
        for (i, _) in md.match_indices(" in `src/` today") {
            let n = md[..i]
                .split(|c: char| !c.is_ascii_digit())
                .rfind(|w| !w.is_empty())
                .and_then(|w| w.parse::<usize>().ok());
            stated.push((page, n));
        }
    }
    assert_eq!(stated.len(), 2, "both pages state the count: {stated:?}");
    for (page, n) in stated {
        assert_eq!(
            n,
            Some(count),
            "{page}: the files naming Framing::Ascii or Codec::Ascii"
        );
    }
}

/// The type an `impl` header names (`crate::config::RelayConfig`, `Clone for
/// Sender<T>`): its last path step, without generics, and the room its path names.
fn impl_target(header: &str) -> (String, Option<String>) {
    let t = header.trim().trim_start_matches('&').trim();
    let t = t.strip_prefix("dyn ").unwrap_or(t);
    let base = t.split('<').next().unwrap_or("").trim();
    let room = base.strip_prefix("crate::").map(room_of_path);
    (base.rsplit("::").next().unwrap_or("").to_string(), room)
}

/// The rooms that define each type (`struct`, `enum`, `union`, `trait`, `type`, or a
/// declaring macro's `[relay] RelayConfig {` and `Framing {`), from the source.
fn type_rooms(files: &[String]) -> std::collections::BTreeMap<String, Vec<String>> {
    let mut rooms = std::collections::BTreeMap::<String, Vec<String>>::new();
    for file in files.iter().filter(|f| f.ends_with(".rs")) {
        for line in production(&repo().join(file)).lines() {
            let mut t = line.trim();
            if t.starts_with("pub") {
                t = t[t.find([' ']).unwrap_or(t.len())..].trim_start();
            }
            let word = |s: &str| -> String {
                s.chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect()
            };
            let keyword = ["struct ", "enum ", "union ", "trait ", "type "]
                .iter()
                .find_map(|k| t.strip_prefix(k).map(word));
            // A declaring macro: `[relay] RelayConfig {`, `Framing {`.
            let declared = || {
                let rest = match t.strip_prefix('[') {
                    Some(r) => r[r.find(']')? + 1..].trim_start(),
                    None => t,
                };
                let name = word(rest);
                let tail = rest[name.len()..].trim();
                let tail = tail.trim_start_matches(|c: char| c.is_ascii_alphanumeric() || c == '_');
                (tail.trim() == "{").then_some(name)
            };
            if let Some(name) = keyword.or_else(declared) {
                if name.starts_with(|c: char| c.is_ascii_uppercase()) {
                    let entry = rooms.entry(name).or_default();
                    entry.push(room(file));
                }
            }
        }
    }
    rooms
}

/// Each policy lives in the room that owns its type (docs/architecture.md "The
/// rooms"): an `impl` block names a type its own room defines, or implements a trait
/// its own room defines; a type's methods written in another room are a tie the
/// drawing does not show.
#[test]
fn every_impl_is_in_the_room_of_its_type() {
    let mut files = Vec::new();
    tree(&repo().join("src"), &mut files);
    let rooms = type_rooms(&files);
    let mut wrong = Vec::new();
    let mut checked = 0;
    for file in files.iter().filter(|f| f.ends_with(".rs")) {
        let here = room(file);
        for line in production(&repo().join(file)).lines() {
            let t = line.trim_start();
            let Some(mut header) = t.strip_prefix("impl") else {
                continue;
            };
            if header.starts_with('<') {
                // Skip the generics, nested `<>` included.
                let mut depth = 0;
                let end = header.char_indices().find(|&(_, c)| {
                    depth += match c {
                        '<' => 1,
                        '>' => -1,
                        _ => 0,
                    };
                    depth == 0
                });
                header = &header[end.map_or(header.len(), |(i, _)| i + 1)..];
            } else if !header.starts_with(' ') {
                continue;
            }
            let header = header.split(['{']).next().unwrap_or("");
            let header = header.split(" where").next().unwrap_or("");
            let ty = match header.split_once(" for ") {
                Some((tr, ty)) => {
                    let (name, room_named) = impl_target(tr);
                    let owned = room_named.as_ref() == Some(&here)
                        || rooms.get(&name).is_some_and(|r| r.contains(&here));
                    if owned {
                        continue;
                    }
                    ty
                }
                None => header,
            };
            let (name, room_named) = impl_target(ty);
            let owners = match room_named {
                Some(r) => vec![r],
                None => rooms.get(&name).cloned().unwrap_or_default(),
            };
            checked += 1;
            if !owners.is_empty() && !owners.contains(&here) {
                wrong.push(format!(
                    "{file}: `impl {}` of a type of `{}`",
                    header.trim(),
                    owners.join("`, `")
                ));
            }
        }
    }
    assert!(
        checked > 100,
        "only {checked} impl blocks found: is the parsing right?"
    );
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// The types each production source file of `src/` defines, by name, with the files
/// that define it: `struct`, `enum`, `union`, `trait`, an exported `type` (an
/// associated type has no `pub`), and a declaring macro's `Framing {` or `[relay]
/// RelayConfig {` at the first indent of a `name! {` block at the margin. Test files
/// (`tests.rs`, `tests/`, the test module) are left out: a test's helper is read
/// where it is.
fn type_names(files: &[String]) -> std::collections::BTreeMap<String, Vec<String>> {
    let mut names = std::collections::BTreeMap::<String, Vec<String>>::new();
    let word = |s: &str| -> String {
        s.chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect()
    };
    let sources = files
        .iter()
        .filter(|f| f.ends_with(".rs") && !f.ends_with("/tests.rs") && !f.contains("/tests/"));
    for file in sources {
        let mut in_macro = false;
        for line in production(&repo().join(file)).lines() {
            let t = line.trim();
            if !line.starts_with(' ') && t.ends_with("! {") {
                in_macro = true;
                continue;
            }
            let name = if in_macro {
                if line.starts_with('}') {
                    in_macro = false;
                }
                let Some(rest) = line.strip_prefix("    ").filter(|r| !r.starts_with(' ')) else {
                    continue;
                };
                let rest = match rest.strip_prefix('[') {
                    Some(r) => r.split_once(']').map_or("", |(_, r)| r.trim_start()),
                    None => rest,
                };
                let name = word(rest);
                let tail = rest[name.len()..].trim_start();
                let tail = tail.trim_start_matches(|c: char| c.is_ascii_uppercase() || c == '_');
                if tail.trim() != "{" {
                    continue;
                }
                name
            } else {
                let (exported, rest) = match t.strip_prefix("pub") {
                    Some(r) if r.starts_with('(') => (true, r.split_once(')').map_or("", |x| x.1)),
                    Some(r) => (true, r),
                    None => (false, t),
                };
                let rest = rest.trim_start();
                let kinds: &[&str] = if exported {
                    &["struct ", "enum ", "union ", "trait ", "type "]
                } else {
                    &["struct ", "enum ", "union ", "trait "]
                };
                let Some(name) = kinds.iter().find_map(|k| rest.strip_prefix(k).map(word)) else {
                    continue;
                };
                name
            };
            if name.starts_with(|c: char| c.is_ascii_uppercase()) {
                let at = names.entry(name).or_default();
                if !at.contains(file) {
                    at.push(file.clone());
                }
            }
        }
    }
    names
}

/// Names still shared, each a rename owed, not a clash argued for: they sit in the
/// rooms being reshaped when this check came (the configuration, the masters' side,
/// the simulator, the command line). The list only shrinks: a name leaves it when its
/// clash is gone (the test says so), and no name joins it.
const SHARED_NAMES_OWED: &[&str] = &[];

/// Types are named by their role (docs/architecture.md "House rules"): no two types of
/// `src/` share a name, so a reader never has to tell two `Request`s or two `Units`
/// apart by their paths.
#[test]
fn no_two_types_share_a_name() {
    let mut files = Vec::new();
    tree(&repo().join("src"), &mut files);
    files.sort();
    let names = type_names(&files);
    assert!(
        names.len() > 300 && names.contains_key("RelayConfig") && names.contains_key("Framing"),
        "only {} type names found: is the parsing right?",
        names.len()
    );
    let shared: Vec<String> = names
        .iter()
        .filter(|(_, at)| at.len() > 1)
        .map(|(name, at)| format!("{name}: {}", at.join(", ")))
        .collect();
    let new: Vec<&String> = shared
        .iter()
        .filter(|s| !SHARED_NAMES_OWED.contains(&s.split(':').next().unwrap()))
        .collect();
    assert!(
        new.is_empty(),
        "types of one name in several files (name the newer by its role):\n{}",
        new.iter()
            .map(|s| s.as_str())
            .collect::<Vec<_>>()
            .join("\n")
    );
    let paid: Vec<&&str> = SHARED_NAMES_OWED
        .iter()
        .filter(|n| names.get(**n).is_none_or(|at| at.len() < 2))
        .collect();
    assert!(
        paid.is_empty(),
        "no longer shared, take them off SHARED_NAMES_OWED: {paid:?}"
    );
}

/// The frame code is pure (docs/architecture.md "The wings"): its production code names
/// no tokio, no I/O, no clock and no other room, so every decoder can be fuzzed alone.
#[test]
fn the_frame_code_is_pure() {
    let mut files = Vec::new();
    tree(&repo().join("src/frame"), &mut files);
    let mut wrong = Vec::new();
    for file in files.iter().filter(|f| f.ends_with(".rs")) {
        let code = production(&repo().join(file));
        for word in [
            "tokio",
            "std::io",
            "std::net",
            "std::fs",
            "Instant",
            "SystemTime",
            "crate::",
        ] {
            let outside = word == "crate::"
                && code
                    .match_indices(word)
                    .any(|(i, _)| !code[i..].starts_with("crate::frame"));
            if (word != "crate::" && code.contains(word)) || outside {
                wrong.push(format!("{file}: names `{word}`"));
            }
        }
    }
    assert!(files.len() > 10, "only {} files in src/frame/", files.len());
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}
