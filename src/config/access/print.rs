//! The security keys as `mbgate check-config` prints them: TOML that reads back to the
//! same configuration, and under each listener who may connect and what they may do.

use super::{AccessRole, ListenAccess, TlsDevice, WriteRules};
use crate::access::Policy;
use crate::config::Setting;

/// A listener's security keys as the `[[listen]]` form prints them, and two comment
/// lines saying who may connect and what they may do (`mbgate check-config`).
pub(crate) fn listen_to_toml(a: &ListenAccess, roles: &[AccessRole]) -> String {
    let mut out = String::new();
    if a.allow.is_some() {
        out += &format!("allow = {}\n", a.allow.print());
    }
    out += &policy_to_toml(&a.policy);
    if a.tls.is_some() {
        out += &format!("tls = {}\n", a.tls.print());
    }
    for line in effective(a, roles) {
        out += &format!("# {line}\n");
    }
    out
}

fn policy_to_toml(p: &Policy) -> String {
    let mut out = String::new();
    if p.read_only {
        out += "read_only = true\n";
    }
    if !p.write.is_empty() {
        out += &format!("write = {}\n", WriteRules(p.write.clone()).print());
    }
    out
}

/// Who may connect to a listener, and what each may do, in words.
pub(crate) fn effective(a: &ListenAccess, roles: &[AccessRole]) -> Vec<String> {
    let who = match &a.allow {
        None => "from everyone (no allow list)".to_owned(),
        Some(l) => format!("only from {l}"),
    };
    let mut lines = Vec::new();
    match &a.tls {
        None => {
            lines.push(format!("who: {who}, plain TCP"));
            lines.push(format!("what: {}", a.policy.describe()));
        }
        Some(t) => {
            lines.push(format!(
                "who: {who}, TLS 1.2/1.3 with a client certificate from {}",
                t.client_ca.display()
            ));
            let no_role = match &t.default_role {
                None => "refused".to_owned(),
                Some(r) => format!("role {r:?}"),
            };
            if roles.is_empty() && t.default_role.is_none() {
                lines.push("what: nothing: no [[role]] tables, every master is refused".into());
            }
            for r in roles {
                let mut what = r.policy.describe();
                if !a.policy.is_open() {
                    what += &format!(", within the listener's {}", a.policy.describe());
                }
                lines.push(format!("what: role {:?}: {what}", r.name));
            }
            lines.push(format!("what: a certificate without a role: {no_role}; with a role no [[role]] names: refused"));
        }
    }
    lines
}

/// The `[[role]]` tables as the file writes them.
pub(crate) fn roles_to_toml(roles: &[AccessRole]) -> String {
    let mut out = Vec::new();
    for r in roles {
        let priority = r
            .priority
            .map_or(String::new(), |p| format!("priority = {p}\n"));
        out.push(format!(
            "[[role]]\nname = {}\n{}{priority}",
            toml::Value::String(r.name.clone()),
            policy_to_toml(&r.policy)
        ));
    }
    out.join("\n")
}

/// A TCP line's `tls` table as `[line.tcp]` prints it.
pub(crate) fn device_to_toml(t: &TlsDevice) -> String {
    format!("tls = {}\n", Some(t.clone()).print())
}
