//! How a user runs this very binary from a shell: what the commands mbgate prints
//! (the demo's banner) start with, so that they run as printed.

use std::path::{Path, PathBuf};

/// `mbgate` when that name on `PATH` is this binary; otherwise the binary's path,
/// relative to the working directory when it lies below it (`target/release/mbgate`
/// after `cargo run --release`), else absolute; quoted for a POSIX shell when needed.
pub(crate) fn command() -> String {
    let Ok(me) = std::env::current_exe().and_then(|p| p.canonicalize()) else {
        return "mbgate".into();
    };
    let path = std::env::var_os("PATH").unwrap_or_default();
    let cwd = std::env::current_dir().ok();
    choose(&me, std::env::split_paths(&path), cwd.as_deref())
}

fn choose(me: &Path, path: impl Iterator<Item = PathBuf>, cwd: Option<&Path>) -> String {
    let name = me.file_name().and_then(|n| n.to_str()).unwrap_or("mbgate");
    // The first match on PATH is what the shell runs.
    let on_path = path
        .map(|dir| dir.join(name))
        .find(|candidate| candidate.is_file());
    if let Some(found) = on_path {
        if found.canonicalize().ok().as_deref() == Some(me) {
            return name.into();
        }
    }
    let shown = match cwd.and_then(|cwd| me.strip_prefix(cwd).ok()) {
        // A bare name would be looked up on PATH: keep a slash in it.
        Some(rel) if rel.parent().is_some_and(|p| !p.as_os_str().is_empty()) => rel.to_path_buf(),
        Some(rel) => Path::new(".").join(rel),
        None => me.to_path_buf(),
    };
    quote(&shown.to_string_lossy())
}

/// Single quotes around anything a shell would split or expand.
fn quote(s: &str) -> String {
    let plain = s
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || "/._-+:@%".contains(c));
    if plain && !s.is_empty() {
        s.into()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn path_relative_absolute_or_quoted() {
        let dir = tempfile::tempdir().unwrap();
        let bin = dir.path().join("target/release");
        std::fs::create_dir_all(&bin).unwrap();
        let me = bin.join("mbgate");
        std::fs::write(&me, b"").unwrap();
        let me = me.canonicalize().unwrap();
        let root = dir.path().canonicalize().unwrap();
        let none = || std::iter::empty::<PathBuf>();
        // On PATH: the bare name.
        assert_eq!(choose(&me, std::iter::once(bin.clone()), None), "mbgate");
        // Below the working directory: relative, with its slash.
        assert_eq!(choose(&me, none(), Some(&root)), "target/release/mbgate");
        assert_eq!(
            choose(&me, none(), Some(&bin.canonicalize().unwrap())),
            "./mbgate"
        );
        // Elsewhere: absolute.
        let other = tempfile::tempdir().unwrap();
        assert_eq!(
            choose(&me, none(), Some(other.path())),
            me.to_string_lossy()
        );
        // Another mbgate first on PATH: not this one, so not the bare name.
        let shadow = other.path().join("mbgate");
        std::fs::write(&shadow, b"").unwrap();
        assert_eq!(
            choose(
                &me,
                std::iter::once(other.path().to_path_buf()),
                Some(&root)
            ),
            "target/release/mbgate"
        );
        assert_eq!(quote("/a b/mbgate"), "'/a b/mbgate'");
        assert_eq!(quote("it's"), r"'it'\''s'");
    }
}
