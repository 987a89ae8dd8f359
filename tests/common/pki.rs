//! Certificates for the Modbus/TCP Security tests, made with the openssl CLI exactly as
//! docs/security.md tells a user to: a CA, the gateway's certificate (for 127.0.0.1
//! and localhost), and masters' certificates with the Modbus role extension
//! (1.3.6.1.4.1.50316.802.1, an ASN.1 UTF8String), one without, one from another CA,
//! one expired.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The Modbus role extension as openssl's `-extfile` writes it.
pub(crate) const ROLE_EXT: &str = "1.3.6.1.4.1.50316.802.1=ASN1:UTF8String:";

/// A folder of certificates and keys: `NAME.pem`, `NAME.key`.
pub(crate) struct Pki {
    pub(crate) dir: PathBuf,
}

fn openssl(dir: &Path, args: &[&str]) {
    let out = Command::new("openssl")
        .args(args)
        .current_dir(dir)
        .output()
        .expect("openssl (Debian: apt-get install openssl; scripts/test does)");
    assert!(
        out.status.success(),
        "openssl {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

impl Pki {
    /// A CA named `ca` in `dir`, and the gateway's certificate `gateway` signed by it.
    pub(crate) fn new(dir: &Path) -> Pki {
        std::fs::create_dir_all(dir).unwrap();
        let pki = Pki {
            dir: dir.to_path_buf(),
        };
        pki.ca("ca");
        pki.sign(
            "gateway",
            "ca",
            "/CN=localhost",
            "subjectAltName=IP:127.0.0.1,DNS:localhost\n",
            30,
        );
        pki
    }

    /// A self-signed CA `name`.
    pub(crate) fn ca(&self, name: &str) {
        openssl(
            &self.dir,
            &[
                "req",
                "-x509",
                "-newkey",
                "rsa:2048",
                "-nodes",
                "-keyout",
                &format!("{name}.key"),
                "-out",
                &format!("{name}.pem"),
                "-days",
                "30",
                "-subj",
                &format!("/CN=test CA {name}"),
            ],
        );
    }

    /// A certificate `name` for `subject` signed by CA `ca`, with the extensions of
    /// `ext` (an openssl extfile), valid `days` (negative: expired already).
    pub(crate) fn sign(&self, name: &str, ca: &str, subject: &str, ext: &str, days: i32) {
        let (key, csr, extfile) = (
            format!("{name}.key"),
            format!("{name}.csr"),
            format!("{name}.ext"),
        );
        openssl(
            &self.dir,
            &[
                "req", "-newkey", "rsa:2048", "-nodes", "-keyout", &key, "-out", &csr, "-subj",
                subject,
            ],
        );
        std::fs::write(self.dir.join(&extfile), ext).unwrap();
        openssl(
            &self.dir,
            &[
                "x509",
                "-req",
                "-in",
                &csr,
                "-CA",
                &format!("{ca}.pem"),
                "-CAkey",
                &format!("{ca}.key"),
                "-CAcreateserial",
                "-out",
                &format!("{name}.pem"),
                "-days",
                &days.to_string(),
                "-extfile",
                &extfile,
            ],
        );
    }

    /// A master's certificate `name` from CA `ca` carrying `role` (none: no extension).
    pub(crate) fn master(&self, name: &str, ca: &str, role: Option<&str>, days: i32) {
        let ext = match role {
            Some(r) => format!("{ROLE_EXT}{r}\n"),
            None => "basicConstraints=CA:FALSE\n".into(),
        };
        self.sign(name, ca, &format!("/CN={name}"), &ext, days);
    }

    pub(crate) fn pem(&self, name: &str) -> String {
        self.dir.join(format!("{name}.pem")).display().to_string()
    }

    pub(crate) fn key(&self, name: &str) -> String {
        self.dir.join(format!("{name}.key")).display().to_string()
    }

    /// `tls = { ... }` of a listener with this folder's gateway certificate and CA.
    pub(crate) fn listen_tls(&self, extra: &str) -> String {
        format!(
            "tls = {{ cert = {:?}, key = {:?}, client_ca = {:?}{extra} }}",
            self.pem("gateway"),
            self.key("gateway"),
            self.pem("ca")
        )
    }
}
