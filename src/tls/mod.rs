//! Modbus/TCP Security (docs/security.md): TLS 1.2 and 1.3 with rustls on the `ring`
//! provider, no OpenSSL. The masters' side ([`server`]: client certificates required,
//! the role read from them, the certificate and key reloaded on SIGHUP), the device
//! side ([`client`]: mbgate verifies the device and presents its own certificate),
//! and the role extension ([`role`]). Loading the PEM files is here, each error naming
//! the key and the file.

pub(crate) mod client;
pub mod role;
pub(crate) mod server;

use rustls::crypto::CryptoProvider;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use rustls::RootCertStore;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The TLS versions mbgate speaks: Modbus/TCP Security asks for TLS 1.2 or later; rustls
/// has no older version at all.
pub(crate) static VERSIONS: &[&rustls::SupportedProtocolVersion] =
    &[&rustls::version::TLS13, &rustls::version::TLS12];

/// The crypto provider: rustls' `ring` (pure Rust and assembly, cross-builds for the
/// Raspberry Pi with the C cross compiler the build already uses).
pub(crate) fn provider() -> Arc<CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// A TLS file that cannot be used: which key names it, the file, and why.
#[derive(Debug, thiserror::Error)]
#[error("{key} = {}: {message}", path.display())]
pub struct TlsError {
    /// The configuration key that names the file (`listen[0].tls.cert`).
    pub(crate) key: String,
    /// The file.
    pub(crate) path: PathBuf,
    /// What is wrong with it.
    pub(crate) message: String,
}

fn error(key: &str, path: &Path, message: impl Into<String>) -> TlsError {
    TlsError {
        key: key.to_owned(),
        path: path.to_owned(),
        message: message.into(),
    }
}

fn pem_message(e: rustls::pki_types::pem::Error, what: &str) -> String {
    use rustls::pki_types::pem::Error as E;
    match e {
        E::Io(e) => format!("cannot read it: {e}"),
        E::NoItemsFound => format!("no {what} in it (PEM expected)"),
        other => format!("not a PEM file of {what}: {other:?}"),
    }
}

/// The certificates of a PEM file, in order; at least one.
pub(crate) fn certificates(
    key: &str,
    path: &Path,
) -> Result<Vec<CertificateDer<'static>>, TlsError> {
    let what = "certificates (BEGIN CERTIFICATE)";
    let iter =
        CertificateDer::pem_file_iter(path).map_err(|e| error(key, path, pem_message(e, what)))?;
    let certs: Vec<_> = iter
        .collect::<Result<_, _>>()
        .map_err(|e| error(key, path, pem_message(e, what)))?;
    if certs.is_empty() {
        return Err(error(key, path, format!("no {what} in it (PEM expected)")));
    }
    Ok(certs)
}

/// The private key of a PEM file (PKCS#8, PKCS#1 or SEC1).
pub(crate) fn private_key(key: &str, path: &Path) -> Result<PrivateKeyDer<'static>, TlsError> {
    PrivateKeyDer::from_pem_file(path).map_err(|e| {
        error(
            key,
            path,
            pem_message(e, "private key (BEGIN PRIVATE KEY, RSA or EC)"),
        )
    })
}

/// The CA certificates of a PEM file as trust anchors.
pub(crate) fn roots(key: &str, path: &Path) -> Result<Arc<RootCertStore>, TlsError> {
    let mut roots = RootCertStore::empty();
    for c in certificates(key, path)? {
        roots.add(c).map_err(|e| {
            error(
                key,
                path,
                format!("a certificate in it is not a usable CA: {e}"),
            )
        })?;
    }
    Ok(Arc::new(roots))
}

/// The chain of `cert_key` and the key of `key_key`, checked to belong together.
pub(crate) fn certified_key(
    (cert_key, cert): (&str, &Path),
    (key_key, key): (&str, &Path),
    provider: &CryptoProvider,
) -> Result<Arc<rustls::sign::CertifiedKey>, TlsError> {
    let chain = certificates(cert_key, cert)?;
    let der = private_key(key_key, key)?;
    rustls::sign::CertifiedKey::from_der(chain, der, provider)
        .map(Arc::new)
        .map_err(|e| {
            error(
                key_key,
                key,
                format!("not usable with {}: {e}", cert.display()),
            )
        })
}

/// Loads every TLS file the configuration names, as the gateway would at start: for
/// `mbgate check-config` and before `mbgate run` starts (a bad file is a bad
/// configuration, exit 2).
pub(crate) fn check(cfg: &crate::config::Config) -> Result<(), TlsError> {
    for (i, l) in cfg.listeners.iter().enumerate() {
        if let Some(t) = &l.access.tls {
            server::Material::load(t, &format!("listen[{i}].tls"))?;
        }
    }
    for (i, d) in cfg.dials.iter().enumerate() {
        if let Some(t) = &d.tls {
            client::Connector::load(&t.client, &d.address, &format!("dial[{i}].tls"))?;
        }
    }
    for (i, line) in cfg.lines.iter().enumerate() {
        if let (Some(address), Some(t)) = (&line.tcp, &line.tcp_tls) {
            client::Connector::load(t, address, &format!("line[{i}].tcp.tls"))?;
        }
    }
    Ok(())
}
