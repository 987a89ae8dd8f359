//! CONTRIBUTING.md "Before you commit" on length, held to src/: no production function
//! over 60 lines unless its doc comment's first line begins `Long because`, and no
//! production file over 600 lines (test modules at a file's end and `tests.rs` files
//! not counted).

use super::map::tree;
use super::repo;

/// The longest a function may be without saying why.
const FUNCTION: usize = 60;
/// The longest a file's production code may be.
const FILE: usize = 600;
/// What begins the first line of a long function's doc comment.
const MARKER: &str = "Long because";

/// A production function: where it is, how long, and its doc comment's first line.
struct Function {
    file: String,
    name: String,
    line: usize,
    lines: usize,
    first_doc: Option<String>,
}

/// The production lines of a file: up to a `#[cfg(test)]` that opens a `mod`.
fn production_lines(text: &str) -> Vec<&str> {
    let lines: Vec<&str> = text.lines().collect();
    let end = (0..lines.len())
        .find(|&i| {
            lines[i].trim() == "#[cfg(test)]"
                && lines
                    .get(i + 1)
                    .is_some_and(|n| n.trim_start().starts_with("mod "))
        })
        .unwrap_or(lines.len());
    lines[..end].to_vec()
}

/// `fn`'s name if `line` opens a function (`pub(crate) async fn name`, ...).
fn opens_function(line: &str) -> Option<&str> {
    let mut rest = line.trim_start();
    if let Some(r) = rest.strip_prefix("pub") {
        rest = match r.strip_prefix('(') {
            Some(r) => r.split_once(')')?.1,
            None => r,
        }
        .trim_start();
    }
    for qualifier in ["const ", "async ", "unsafe "] {
        if let Some(r) = rest.strip_prefix(qualifier) {
            rest = r.trim_start();
        }
    }
    let name = rest.strip_prefix("fn ")?;
    let end = name
        .find(|c: char| !(c.is_alphanumeric() || c == '_'))
        .unwrap_or(name.len());
    (end > 0).then(|| &name[..end])
}

/// The first line of the doc comment right above line `at` (attributes between
/// skipped).
fn first_doc(lines: &[&str], at: usize) -> Option<String> {
    let mut i = at;
    while i > 0 && lines[i - 1].trim_start().starts_with("#[") {
        i -= 1;
    }
    let mut first = None;
    while i > 0 && lines[i - 1].trim_start().starts_with("///") {
        i -= 1;
        first = Some(lines[i].trim_start()[3..].trim().to_string());
    }
    first
}

/// The production functions of `lines` (a file's), from each `fn` line to the `}` at its
/// indent, both counted.
fn functions(file: &str, lines: &[&str]) -> Vec<Function> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let Some(name) = opens_function(lines[i]) else {
            i += 1;
            continue;
        };
        let indent = lines[i].len() - lines[i].trim_start().len();
        // The signature may run over several lines; a `;` ends a declaration.
        let mut j = i;
        let ends = |l: &str, c: char| l.trim_end().ends_with(c);
        while j < lines.len() && !ends(lines[j], '{') && !ends(lines[j], ';') {
            j += 1;
        }
        if j == lines.len() || ends(lines[j], ';') {
            i = j + 1;
            continue;
        }
        let mut k = j + 1;
        while k < lines.len()
            && !(lines[k].len() - lines[k].trim_start().len() == indent
                && lines[k].trim_start().starts_with('}'))
        {
            k += 1;
        }
        out.push(Function {
            file: file.to_string(),
            name: name.to_string(),
            line: i + 1,
            lines: k.min(lines.len() - 1) - i + 1,
            first_doc: first_doc(lines, i),
        });
        i = k + 1;
    }
    out
}

/// The production files of src/ (no `tests.rs`, nothing under a `tests/` folder) and
/// their production lines.
fn sources() -> Vec<(String, String)> {
    let mut files = Vec::new();
    tree(&repo().join("src"), &mut files);
    files.sort();
    files
        .into_iter()
        .filter(|f| f.ends_with(".rs") && !f.ends_with("/tests.rs") && !f.contains("/tests/"))
        .map(|f| {
            let text = std::fs::read_to_string(repo().join(&f)).unwrap();
            (f, text)
        })
        .collect()
}

/// A production function over 60 lines begins its doc comment with `Long because`
/// (a table of cases, a `select!` loop whose arms share state): anything else is split
/// by what it does.
#[test]
fn every_long_function_says_why_it_is_long() {
    let mut all = Vec::new();
    for (file, text) in sources() {
        all.extend(functions(&file, &production_lines(&text)));
    }
    assert!(
        all.len() > 1000 && all.iter().any(|f| f.name == "main" && f.lines < FUNCTION),
        "only {} functions found: is the parsing right?",
        all.len()
    );
    let long: Vec<&Function> = all.iter().filter(|f| f.lines > FUNCTION).collect();
    let unsaid: Vec<String> = long
        .iter()
        .filter(|f| {
            !f.first_doc
                .as_deref()
                .is_some_and(|d| d.starts_with(MARKER))
        })
        .map(|f| format!("{}:{} {} ({} lines)", f.file, f.line, f.name, f.lines))
        .collect();
    assert!(
        unsaid.is_empty(),
        "functions over {FUNCTION} lines: split them by what they do, or begin the doc \
         comment's first line with `{MARKER}` and say why:\n{}",
        unsaid.join("\n")
    );
}

/// No production file of src/ over 600 lines: a coherent part moves to a file of its
/// own (its first line its job, its row on the map).
#[test]
fn no_production_file_is_over_600_lines() {
    let long: Vec<String> = sources()
        .iter()
        .map(|(file, text)| (file, production_lines(text).len()))
        .filter(|(_, n)| *n > FILE)
        .map(|(file, n)| format!("{file}: {n} lines"))
        .collect();
    assert!(
        long.is_empty(),
        "files over {FILE} production lines (test modules and tests.rs apart):\n{}",
        long.join("\n")
    );
}
