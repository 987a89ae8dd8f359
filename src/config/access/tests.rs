//! The security keys of the file: their mistakes named, and what check-config prints.

use super::*;
use crate::config::{parse, to_toml};

#[test]
fn ranges() {
    assert_eq!(range("10-20", 255), Ok((10, 20)));
    assert_eq!(range(" 0 - 65535 ", 65535), Ok((0, 65535)));
    assert!(range("20-10", 255).unwrap_err().message.contains("empty"));
    assert!(range("0-256", 255).is_err());
    assert!(range("7", 255).is_err());
}

fn error(text: &str) -> String {
    parse(text, "t.toml").unwrap_err().to_string()
}

/// Each mistake is named with its file, line, column and key, and says what to do.
#[test]
fn mistakes_are_named_precisely() {
    let listen = "[[listen]]\naddress = \"0.0.0.0:502\"\n";
    let cases = [
        (format!("{listen}allow = [\"10.0.0.1/24\"]\n"),
         "t.toml:3:10: listen[0].allow: \"10.0.0.1/24\" has bits set past its prefix length: did you mean \"10.0.0.0/24\"?"),
        (format!("{listen}allow = []\n"),
         "t.toml:3:9: listen[0].allow: must list at least one address (leave allow out to take everyone)"),
        (format!("{listen}read_only = true\nwrite = [{{ units = [1] }}]\n"),
         "t.toml:3:13: listen[0].read_only: read_only = true refuses every write: give listen[0].read_only or listen[0].write, not both"),
        (format!("{listen}write = [{{ unit = [1] }}]\n"),
         "t.toml:3:12: listen[0].write[0].unit: unknown key; expected one of units, functions, addresses (did you mean `units`?)"),
        (format!("{listen}write = [{{ functions = [3] }}]\n"),
         "t.toml:3:25: listen[0].write[0].functions: function 3 only reads"),
        (format!("{listen}write = [{{ addresses = \"9-1\" }}]\n"),
         "t.toml:3:24: listen[0].write[0].addresses: the range \"9-1\" is empty"),
        (format!("{listen}write = [{{}}]\n"),
         "t.toml:3:10: listen[0].write[0]: an empty rule permits every write"),
        (format!("{listen}tls = {{ cert = \"c\", key = \"k\" }}\n"),
         "t.toml:3:7: listen[0].tls.client_ca: missing: the CA masters' certificates must chain to"),
        (format!("{listen}tls = {{ cert = \"c\", key = \"k\", client_ca = \"a\", default_role = \"op\" }}\n[[role]]\nname = \"viewer\"\n"),
         "t.toml:3:64: listen[0].tls.default_role: no [[role]] is named \"op\"; the roles are viewer"),
        (format!("{listen}tls = {{ cert = \"c\", key = \"k\", client_ca = \"a\", handshake_timeout = 1 }}\n"),
         "listen[0].tls.handshake_timeout: unknown key; expected one of cert, key, client_ca, default_role, handshake_timeout_ms (did you mean `handshake_timeout_ms`?)"),
        ("[[role]]\nname = \"a\"\n[[role]]\nname = \"a\"\n".into(),
         "t.toml:4:8: role[1].name: role \"a\" is also role[0]"),
        ("[[role]]\nread_only = true\n".into(), "t.toml:1:1: role[0].name: missing"),
        ("[tcp]\nlisten = \"0.0.0.0:502\"\nallow = [\"10.0.0.0/8\"]\n".into(),
         "t.toml:3:1: tcp.allow: allow belongs in a [[listen]] table"),
        ("[[line]]\ntcp = { address = \"h:802\", tls = { cert = \"c\", key = \"k\" } }\n".into(),
         "line[0].tcp.tls.device_ca: missing: the CA the device's certificate must chain to"),
    ];
    let wrong: Vec<String> = cases
        .iter()
        .map(|(text, want)| (text, want, error(text)))
        .filter(|(_, want, got)| !got.starts_with(*want) && !got.contains(*want))
        .map(|(text, want, got)| format!("{text}\n got: {got}\nwant: {want}"))
        .collect();
    assert!(wrong.is_empty(), "{}", wrong.join("\n\n"));
}

/// check-config prints the security keys and who and what in comments; the text
/// reads back to the same configuration.
#[test]
fn printed_and_read_back_with_who_and_what() {
    let text = "[[line]]\ntcp = { address = \"10.0.0.9:802\", tls = { cert = \"/c.pem\", key = \"/c.key\", device_ca = \"/ca.pem\", server_name = \"plc\" } }\n\
        [[listen]]\naddress = \"0.0.0.0:502\"\nallow = [\"10.0.0.0/24\", \"::ffff:192.168.1.0/120\"]\nread_only = true\n\
        [[listen]]\naddress = \"0.0.0.0:802\"\nwrite = [{ units = [1, 2, 3], functions = [6], addresses = \"0-99\" }, { units = [9] }]\n\
        tls = { cert = \"/g.pem\", key = \"/g.key\", client_ca = \"/ca.pem\", default_role = \"viewer\" }\n\
        [[role]]\nname = \"operator\"\nwrite = [{ addresses = 7 }]\n[[role]]\nname = \"viewer\"\nread_only = true\n";
    let cfg = parse(text, "t").unwrap();
    let printed = to_toml(&cfg);
    assert_eq!(parse(&printed, "printed").unwrap(), cfg, "{printed}");
    for said in [
        "allow = [\"10.0.0.0/24\", \"192.168.1.0/24\"]\nread_only = true\n# who: only from 10.0.0.0/24, 192.168.1.0/24, plain TCP\n# what: read only\n",
        "write = [{ units = [\"1-3\"], functions = [6], addresses = \"0-99\" }, { units = [9] }]\n",
        "# who: from everyone (no allow list), TLS 1.2/1.3 with a client certificate from /ca.pem\n",
        "# what: role \"operator\": read, and write only as { addresses = \"7-7\" }, within the listener's read, and write only as",
        "# what: a certificate without a role: role \"viewer\"; with a role no [[role]] names: refused\n",
        "tls = { cert = \"/c.pem\", key = \"/c.key\", device_ca = \"/ca.pem\", server_name = \"plc\" }\n",
        "[[role]]\nname = \"viewer\"\nread_only = true\n",
    ] {
        assert!(printed.contains(said), "{said}\nnot in:\n{printed}");
    }
}

/// A listener's and a role's `priority`: read, said by check-config, printed and read
/// back; out of range, named.
#[test]
fn priority_classes_of_listeners_and_roles() {
    let text = "[[listen]]\naddress = \"127.0.0.1:1502\"\npriority = 2\n\
                [[listen]]\naddress = \"127.0.0.1:1503\"\n\
                [[role]]\nname = \"scada\"\npriority = 5\n";
    let cfg = parse(text, "t.toml").unwrap();
    let classes: Vec<u8> = cfg.listeners.iter().map(|l| l.priority).collect();
    assert_eq!(classes, [2, 0]);
    assert_eq!(cfg.roles[0].priority, Some(5));
    assert!(crate::config::describe::summary(&cfg)
        .contains("127.0.0.1:1502 for Modbus/TCP masters, at most 32 at once, priority class 2"));
    assert_eq!(parse(&to_toml(&cfg), "again").unwrap(), cfg);
    // One listener with a priority is no longer the old form's [tcp].
    let one = parse(
        "[[listen]]\naddress = \"127.0.0.1:1502\"\npriority = 1\n",
        "t",
    )
    .unwrap();
    assert_eq!(one.listeners[0].priority, 1);
    assert_eq!(
        error("[[listen]]\naddress = \"127.0.0.1:1502\"\npriority = 8\n"),
        "t.toml:3:12: listen[0].priority: must be 0 (the default, the lowest) to 7, got 8"
    );
    assert_eq!(
        error("[[role]]\nname = \"x\"\npriority = -1\n"),
        "t.toml:3:12: role[0].priority: must be 0 (the default, the lowest) to 7, got -1"
    );
}
