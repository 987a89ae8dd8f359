//! scripts/test's install step on a machine where the tests' Debian packages are
//! missing (a PATH without their commands): it says what it will install before doing
//! it, installs with --no-install-recommends, never a package whose install would
//! upgrade an installed one (apt-get's dry run says so), installs nothing with
//! --no-install, and everything with CI=true. Once with the real apt-get's dry run,
//! once with a stand-in apt-get that records what it is asked (no root needed).

use crate::common;
use common::repo;
use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::process::Command;

/// The commands of the optional peers scripts/test checks for.
const HIDDEN: &[&str] = &["chromium", "mbpoll", "tshark", "zsh", "fish", "man"];

/// A directory of links to every command on PATH but `HIDDEN` (and `replaced`, which
/// the caller writes itself): a PATH on which those packages look missing.
fn path_without(dir: &Path, replaced: &[&str]) -> String {
    let bin = dir.join("bin");
    std::fs::create_dir_all(&bin).unwrap();
    let path = std::env::var_os("PATH").unwrap();
    for d in std::env::split_paths(&path) {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries.flatten() {
            let name = e.file_name();
            let name = name.to_str().unwrap_or("");
            if HIDDEN.contains(&name) || replaced.contains(&name) || bin.join(name).exists() {
                continue;
            }
            let _ = std::os::unix::fs::symlink(e.path(), bin.join(name));
        }
    }
    bin.display().to_string()
}

fn script(path: &Path, text: &str) {
    std::fs::write(path, text).unwrap();
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o755)).unwrap();
}

/// scripts/test ARGS with `path` as PATH and `env`: (exit code, stderr).
fn run(path: &str, args: &[&str], env: &[(&str, &str)]) -> (i32, String) {
    let mut cmd = Command::new(repo().join("scripts/test"));
    cmd.args(args).env("PATH", path).env_remove("CI");
    for (k, v) in env {
        cmd.env(k, v);
    }
    let out = cmd.output().expect("run scripts/test");
    let text = String::from_utf8_lossy(&out.stderr).into_owned();
    (out.status.code().unwrap_or(-1), text)
}

/// The real apt-get, dry run only (`--install-plan`, no root needed): the packages of
/// the hidden commands are named, with --no-install-recommends, and nothing is upgraded.
#[test]
fn the_install_plan_names_the_missing_packages_and_upgrades_nothing() {
    if !common::peer("apt-get", "apt") {
        return;
    }
    let dir = common::tempdir();
    let path = path_without(dir.path(), &[]);
    let (code, err) = run(&path, &["--install-plan"], &[]);
    eprintln!("{err}");
    assert_eq!(code, 0, "{err}");
    let needed = err
        .lines()
        .find(|l| l.contains("the tests need Debian packages not installed here"))
        .unwrap_or_else(|| panic!("no list of missing packages: {err}"));
    for pkg in ["chromium", "mbpoll", "tshark", "zsh", "fish", "man-db"] {
        assert!(needed.contains(pkg), "{pkg} not named: {needed}");
    }
    // Each package is either to be installed, upgrading nothing, or refused for
    // what it would upgrade.
    let plan = err
        .lines()
        .find(|l| l.contains("with --no-install-recommends; with what they depend on"));
    if let Some(plan) = plan {
        assert!(plan.ends_with("upgraded: none"), "{plan}");
    }
    assert!(err.contains("install plan only: nothing installed") || plan.is_none());
    assert!(
        plan.is_some() || err.contains("not installing"),
        "neither installed nor refused: {err}"
    );
}

/// A stand-in apt-get whose dry run says installing chromium would upgrade libc6:
/// run as root (a stand-in `id`), scripts/test says what it installs before it does,
/// installs the rest with --no-install-recommends and not chromium; with CI=true it
/// installs chromium too; with --no-install (or MBGATE_TEST_INSTALL=no) nothing.
#[test]
fn a_package_that_would_upgrade_another_is_not_installed_unless_in_ci() {
    let dir = common::tempdir();
    let path = path_without(dir.path(), &["apt-get", "id"]);
    let bin = dir.path().join("bin");
    let calls = dir.path().join("calls");
    script(&bin.join("id"), "#!/bin/sh\necho 0\n");
    script(
        &bin.join("apt-get"),
        &format!(
            r#"#!/bin/sh
case " $* " in
*" -s "*)
    for p in "$@"; do
        case "$p" in
        -*|install) ;;
        chromium) echo "Inst libc6 [2.36-9] (2.36-10 Debian:12 [amd64])"; echo "Inst chromium (120 Debian:12 [amd64])" ;;
        *) echo "Inst $p (1.0 Debian:12 [amd64])" ;;
        esac
    done ;;
*) echo "apt-get $*" >>{calls}; echo "APT-GET CALLED" >&2 ;;
esac
"#,
            calls = calls.display()
        ),
    );
    let (code, err) = run(&path, &["--install-only"], &[]);
    assert_eq!(code, 0, "{err}");
    let done = std::fs::read_to_string(&calls).unwrap_or_default();
    let install = done
        .lines()
        .find(|l| l.contains(" install "))
        .unwrap_or_else(|| panic!("no install: {done}\n{err}"));
    assert!(install.contains("--no-install-recommends"), "{install}");
    assert!(!install.contains("chromium"), "{install}");
    for pkg in ["mbpoll", "tshark", "zsh", "fish", "man-db"] {
        assert!(install.contains(pkg), "{pkg}: {install}");
    }
    assert!(
        err.contains("not installing chromium: it would upgrade libc6"),
        "{err}"
    );
    // Said before it was done.
    let said = err.find("scripts/test: installing ").expect(&err);
    let called = err.find("APT-GET CALLED").expect(&err);
    assert!(said < called, "{err}");
    assert!(err.contains("upgraded: none"), "{err}");

    std::fs::remove_file(&calls).unwrap();
    let (code, err) = run(&path, &["--install-only"], &[("CI", "true")]);
    assert_eq!(code, 0, "{err}");
    let done = std::fs::read_to_string(&calls).unwrap();
    assert!(
        done.lines()
            .any(|l| l.contains(" install ") && l.contains("chromium")),
        "CI installs everything: {done}"
    );

    std::fs::remove_file(&calls).unwrap();
    for (args, env) in [
        (&["--no-install", "--install-only"][..], &[][..]),
        (
            &["--install-only"][..],
            &[("MBGATE_TEST_INSTALL", "no")][..],
        ),
    ] {
        let (code, err) = run(&path, args, env);
        assert_eq!(code, 0, "{err}");
        assert!(!calls.exists(), "installed though told not to: {err}");
        assert!(err.contains("not installing them"), "{err}");
        assert!(
            err.contains("without chromium (Debian package chromium): the tests that need it skip"),
            "{err}"
        );
    }
}
