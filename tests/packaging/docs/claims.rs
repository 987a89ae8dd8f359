//! docs/architecture.md "Who does what" is the code's: the files that use clap, install
//! signal handlers and hold unsafe blocks are the ones its lines name, no more, no
//! fewer (a directory named covers its files, and must hold one of them).

use super::map::{production, tree};
use crate::common::repo;

/// The backquoted paths of the line of "Who does what" that begins `- {what}:`.
fn named(page: &str, what: &str) -> Vec<String> {
    let section = &page[page.find("### Who does what").expect("the section")..];
    let start = section
        .find(&format!("\n- {what}:"))
        .unwrap_or_else(|| panic!("a line for {what}"));
    let item = &section[start + 1..];
    let end = item[2..].find("\n- ").map_or(item.len(), |e| e + 2);
    let end = end.min(item.find("\n\n").unwrap_or(item.len()));
    item[..end]
        .split('`')
        .skip(1)
        .step_by(2)
        .filter(|p| p.starts_with("src/"))
        .map(str::to_string)
        .collect()
}

/// The files of src/ whose production code (no comments, no test module) has `uses`.
fn using(uses: &dyn Fn(&str) -> bool) -> Vec<String> {
    let mut files = Vec::new();
    tree(&repo().join("src"), &mut files);
    files
        .into_iter()
        .filter(|f| f.ends_with(".rs"))
        .filter(|f| uses(&production(&repo().join(f))))
        .collect()
}

fn check(what: &str, uses: &dyn Fn(&str) -> bool) {
    let page = std::fs::read_to_string(repo().join("docs/architecture.md")).unwrap();
    let names = named(&page, what);
    assert!(!names.is_empty(), "{what}: no file named");
    let found = using(uses);
    let covers = |name: &String, file: &String| {
        if name.ends_with('/') {
            file.starts_with(name.as_str())
        } else {
            file == name
        }
    };
    let mut wrong = Vec::new();
    for f in &found {
        if !names.iter().any(|n| covers(n, f)) {
            wrong.push(format!(
                "{f} has {what} but architecture.md does not name it"
            ));
        }
    }
    for n in &names {
        if !found.iter().any(|f| covers(n, f)) {
            wrong.push(format!(
                "architecture.md names {n} for {what}, which has none"
            ));
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

#[test]
fn the_files_that_use_clap_are_the_ones_named() {
    check("clap", &|code| {
        code.contains("clap::") || code.contains("use clap")
    });
}

#[test]
fn the_files_that_install_signal_handlers_are_the_ones_named() {
    check("Signal handlers", &|code| code.contains("SignalKind::"));
}

#[test]
fn the_files_with_unsafe_blocks_are_the_ones_named() {
    check("Unsafe blocks", &|code| {
        code.contains("unsafe {") || code.contains("unsafe fn") || code.contains("unsafe impl")
    });
}
