# Shared by the scripts that build, package and check mbgate (sourced, not run): the
# cache directory, Debian packages and the pinned cargo-deb, a free local port, the
# runner baked into each test system, and reading the result lines of
# scripts/service-checks.

# Downloads and built base systems, reused by the next run.
cache=${XDG_CACHE_HOME:-$HOME/.cache}/mbgate-pi
mirror=${MBGATE_DEBIAN_MIRROR:-http://deb.debian.org/debian}
suite=bookworm

say() { echo "$(basename "$0"): $*" >&2; }
die() {
    say "$*"
    exit 1
}

# ensure_commands "cmd:package ..." installs the packages whose command is missing (in
# one apt-get call, so apt resolves them together), then checks every command again:
# a command still missing stops the script here, named with its package, not minutes
# later where it is first used.
ensure_commands() {
    local missing=() pair
    for pair in "$@"; do
        command -v "${pair%%:*}" >/dev/null 2>&1 || missing+=("${pair#*:}")
    done
    if [ ${#missing[@]} -gt 0 ]; then
        [ "$(id -u)" = 0 ] || die "needs root (debootstrap, mounts): missing ${missing[*]}"
        say "installing ${missing[*]}"
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq
        apt-get install -y -qq --no-install-recommends "${missing[@]}" >&2
    fi
    require_commands "$@"
}

# require_commands "cmd:package ...": stops with the first command that is not there.
require_commands() {
    local pair
    for pair in "$@"; do
        command -v "${pair%%:*}" >/dev/null 2>&1 ||
            die "${pair%%:*} not found (Debian package ${pair#*:}); install it and run again"
    done
}

# ensure_packages PACKAGE...: installs those not installed.
ensure_packages() {
    local missing=() pkg
    for pkg in "$@"; do
        dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    [ "$(id -u)" = 0 ] || die "needs root: missing ${missing[*]}"
    say "installing ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends "${missing[@]}" >&2
}

# A TCP port on 127.0.0.1 that nothing listens on now.
free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

# cargo-deb at the version .ci/run pins.
ensure_cargo_deb() {
    local version
    version=$(sed -n 's/^CARGO_DEB_VERSION=//p' .ci/run)
    if [ "$(cargo deb --version 2>/dev/null)" != "cargo-deb $version" ]; then
        cargo install cargo-deb --locked --version "$version"
    fi
}

# The runner baked into every base system: at boot, after multi-user.target, run
# /run/payload/run (bound there by systemd-nspawn, or the disk labelled mbpayload under
# qemu), then power off. The payload changes every run; this stays the same.
runner_unit='[Unit]
Description=mbgate checks: run /run/payload/run, then power off
After=multi-user.target

[Service]
Type=oneshot
TimeoutStartSec=infinity
ExecStart=/usr/local/sbin/mbgate-ring
ExecStopPost=/usr/bin/systemctl --no-block poweroff

[Install]
WantedBy=multi-user.target'
runner_script='#!/bin/sh
# Runs the checks handed to this system in /run/payload (see mbgate-ring.service).
if [ ! -x /run/payload/run ]; then
    mkdir -p /run/payload
    mount -o ro LABEL=mbpayload /run/payload || exit 1
fi
exec /run/payload/run'

# install_runner ROOT: the runner, enabled; no login prompts on the consoles.
install_runner() {
    local root=$1
    mkdir -p "$root/usr/local/sbin" "$root/etc/systemd/system/multi-user.target.wants"
    printf '%s\n' "$runner_script" >"$root/usr/local/sbin/mbgate-ring"
    chmod 0755 "$root/usr/local/sbin/mbgate-ring"
    printf '%s\n' "$runner_unit" >"$root/etc/systemd/system/mbgate-ring.service"
    ln -sf /etc/systemd/system/mbgate-ring.service \
        "$root/etc/systemd/system/multi-user.target.wants/mbgate-ring.service"
    for getty in console-getty.service serial-getty@hvc0.service getty@tty1.service; do
        ln -sf /dev/null "$root/etc/systemd/system/$getty"
    done
    echo mbgate-test >"$root/etc/hostname"
}

# A short key for what went into a base system, so a changed recipe builds a new one.
recipe_key() { printf '%s\n' "$@" "$runner_unit" "$runner_script" | sha256sum | cut -c1-12; }

# follow_results FILE PID: print the result lines as they arrive until PID exits, and
# the figures measured beside them (FIGURE lines: a measurement, not a check).
follow_results() {
    local file=$1 pid=$2
    tail -n +1 -F --pid="$pid" "$file" 2>/dev/null | grep --line-buffered -E '^(PASS|FAIL|SKIP|FIGURE|DONE) ' || true
}

# verdict FILE TOTAL MAX_SKIPS: 0 if FILE has its DONE line, no failure, TOTAL checks
# that passed or were skipped, and at most MAX_SKIPS of them skipped.
verdict() {
    local file=$1 total=$2 max_skips=$3 passes fails skips
    passes=$(grep -c '^PASS ' "$file" || true)
    fails=$(grep -c '^FAIL ' "$file" || true)
    skips=$(grep -c '^SKIP ' "$file" || true)
    if ! grep -q '^DONE ' "$file"; then
        say "the checks did not finish (see the log above)"
        return 1
    fi
    if [ "$fails" -gt 0 ] || [ $((passes + skips)) -ne "$total" ] || [ "$skips" -gt "$max_skips" ]; then
        say "$passes passed, $skips skipped (want $total checks, at most $max_skips skipped), $fails failed"
        return 1
    fi
    say "$passes checks passed, $skips skipped"
}
