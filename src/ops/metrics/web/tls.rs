//! The metrics listener's TLS (docs/watching.md "Behind TLS and a password"): the
//! rustls server configuration a web configuration file's `tls_server_config` asks
//! for, on the masters' side's `ring` provider and PEM readers (`crate::tls`):
//! its certificate and key, client certificates verified against `client_ca_file`
//! when asked (`client_auth_type`), the TLS versions, and exporter-toolkit's
//! `cipher_suites` and `curve_preferences` by their Go names.

use super::file::{At, ClientAuth, Pem, TlsFile, Version};
use super::WebConfigError;
use crate::tls::{certificates, private_key, provider, roots, TlsError};
use rustls::crypto::CryptoProvider;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use rustls::server::WebPkiClientVerifier;
use rustls::sign::{CertifiedKey, SingleCertAndKey};
use rustls::{RootCertStore, ServerConfig};
use std::path::Path;
use std::sync::Arc;

/// What the listener serves TLS with, and its words for the log.
#[derive(Debug)]
pub(crate) struct WebTls {
    pub(crate) config: Arc<ServerConfig>,
    /// `TLS 1.2/1.3, client certificates required (CA /etc/mbgate/ca.pem)`.
    pub(crate) said: String,
}

fn at_error(file: &Path, at: &At, message: String) -> WebConfigError {
    WebConfigError::At {
        file: file.to_owned(),
        line: at.line,
        column: at.column,
        key: at.key.clone(),
        message,
    }
}

/// A PEM file's error from the masters' side's readers, at the key that names it.
fn pem_error<'a>(file: &'a Path, at: &'a At) -> impl Fn(TlsError) -> WebConfigError + 'a {
    move |e| at_error(file, at, format!("{}: {}", e.path.display(), e.message))
}

fn chain(
    file: &Path,
    (pem, at): &(Pem, At),
) -> Result<Vec<CertificateDer<'static>>, WebConfigError> {
    match pem {
        Pem::File(p) => certificates(&at.key, p).map_err(pem_error(file, at)),
        Pem::Inline(text) => {
            let certs: Result<Vec<_>, _> =
                CertificateDer::pem_slice_iter(text.as_bytes()).collect();
            match certs {
                Ok(c) if !c.is_empty() => Ok(c),
                _ => Err(at_error(
                    file,
                    at,
                    "no certificate (BEGIN CERTIFICATE) in it".into(),
                )),
            }
        }
    }
}

fn key(file: &Path, (pem, at): &(Pem, At)) -> Result<PrivateKeyDer<'static>, WebConfigError> {
    match pem {
        Pem::File(p) => private_key(&at.key, p).map_err(pem_error(file, at)),
        Pem::Inline(text) => PrivateKeyDer::from_pem_slice(text.as_bytes()).map_err(|_| {
            at_error(
                file,
                at,
                "no private key (BEGIN PRIVATE KEY, RSA or EC) in it".into(),
            )
        }),
    }
}

fn ca(file: &Path, pem: &(Pem, At)) -> Result<Arc<RootCertStore>, WebConfigError> {
    let (p, at) = pem;
    if let Pem::File(path) = p {
        return roots(&at.key, path).map_err(pem_error(file, at));
    }
    let mut store = RootCertStore::empty();
    for c in chain(file, pem)? {
        store.add(c).map_err(|e| {
            at_error(
                file,
                at,
                format!("a certificate in it is not a usable CA: {e}"),
            )
        })?;
    }
    Ok(Arc::new(store))
}

/// The ring provider with only the suites and groups `t` names, in its order.
fn narrowed(file: &Path, t: &TlsFile) -> Result<(CryptoProvider, bool), WebConfigError> {
    let mut p = Arc::unwrap_or_clone(provider());
    let mut tls12 = true;
    if let Some((names, at)) = &t.cipher_suites {
        p.cipher_suites = suites(file, names, at, &p.cipher_suites)?;
        tls12 = p.cipher_suites.iter().any(|s| s.tls13().is_none());
    }
    if let Some((names, at)) = &t.curves {
        let chosen = curves(file, names, at, &p.kx_groups)?;
        if !chosen.is_empty() {
            p.kx_groups = chosen;
        }
    }
    Ok((p, tls12))
}

/// The TLS 1.2 suites `names` (at `at`) of the provider's `all`, in their order, then
/// every TLS 1.3 suite (which the file does not choose).
fn suites(
    file: &Path,
    names: &[String],
    at: &At,
    all: &[rustls::SupportedCipherSuite],
) -> Result<Vec<rustls::SupportedCipherSuite>, WebConfigError> {
    let twelve: Vec<&str> = all
        .iter()
        .filter(|s| s.tls13().is_none())
        .filter_map(|s| s.suite().as_str())
        .collect();
    let mut chosen = Vec::new();
    for name in names {
        // Go's name for the ChaCha20 suites leaves the hash off.
        let full = match name.as_str() {
            "TLS_ECDHE_RSA_WITH_CHACHA20_POLY1305" | "TLS_ECDHE_ECDSA_WITH_CHACHA20_POLY1305" => {
                format!("{name}_SHA256")
            }
            _ => name.clone(),
        };
        // TLS 1.3's suites are not chosen by the file (as in Go): named, they are
        // taken as they are.
        if [
            "TLS_AES_128_GCM_SHA256",
            "TLS_AES_256_GCM_SHA384",
            "TLS_CHACHA20_POLY1305_SHA256",
        ]
        .contains(&name.as_str())
        {
            continue;
        }
        match all.iter().find(|s| s.suite().as_str() == Some(full.as_str())) {
            Some(s) => chosen.push(*s),
            None => {
                return Err(at_error(
                    file,
                    at,
                    format!(
                        "{name}: not a TLS 1.2 suite mbgate offers (rustls offers only AEAD suites with forward secrecy); expected some of {}",
                        twelve.join(", ")
                    ),
                ))
            }
        }
    }
    chosen.extend(all.iter().filter(|s| s.tls13().is_some()).copied());
    Ok(chosen)
}

/// The key exchange groups `names` (at `at`, by Go's names) of the provider's `all`.
fn curves(
    file: &Path,
    names: &[String],
    at: &At,
    all: &[&'static dyn rustls::crypto::SupportedKxGroup],
) -> Result<Vec<&'static dyn rustls::crypto::SupportedKxGroup>, WebConfigError> {
    let mut chosen = Vec::new();
    for name in names {
        let ours = match name.as_str() {
            "X25519" => "X25519",
            "CurveP256" => "secp256r1",
            "CurveP384" => "secp384r1",
            _ => "",
        };
        match all.iter().find(|g| g.name().as_str() == Some(ours)) {
            Some(g) => chosen.push(*g),
            None => {
                return Err(at_error(
                    file,
                    at,
                    format!("{name}: not a curve mbgate offers; expected some of X25519, CurveP256, CurveP384"),
                ))
            }
        }
    }
    Ok(chosen)
}

/// How `t` treats client certificates: `builder` with its verifier (none without a
/// client CA), and how the log says it.
fn client_auth(
    file: &Path,
    t: &TlsFile,
    builder: rustls::ConfigBuilder<ServerConfig, rustls::WantsVerifier>,
    provider: &Arc<CryptoProvider>,
) -> Result<
    (
        rustls::ConfigBuilder<ServerConfig, rustls::server::WantsServerCert>,
        String,
    ),
    WebConfigError,
> {
    Ok(match (&t.client_ca, t.client_auth.0) {
        (Some(pem), auth @ (ClientAuth::IfGiven | ClientAuth::Required)) => {
            let roots = ca(file, pem)?;
            let verifier = WebPkiClientVerifier::builder_with_provider(roots, provider.clone());
            let verifier = if auth == ClientAuth::IfGiven {
                verifier.allow_unauthenticated()
            } else {
                verifier
            };
            let verifier = verifier.build().map_err(|e| {
                at_error(file, &pem.1, format!("cannot verify clients with it: {e}"))
            })?;
            let how = if auth == ClientAuth::Required {
                "required"
            } else {
                "verified when given"
            };
            let ca = match &pem.0 {
                Pem::File(p) => p.display().to_string(),
                Pem::Inline(_) => "client_ca".into(),
            };
            (
                builder.with_client_cert_verifier(verifier),
                format!(", client certificates {how} (CA {ca})"),
            )
        }
        _ => (builder.with_no_client_auth(), String::new()),
    })
}

/// The server configuration of `t` (from the web configuration file `file`).
pub(crate) fn load(t: &TlsFile, file: &Path) -> Result<WebTls, WebConfigError> {
    let (provider, tls12) = narrowed(file, t)?;
    let provider = Arc::new(provider);
    let mut versions: Vec<&'static rustls::SupportedProtocolVersion> = Vec::new();
    if t.max_version >= Version::Tls13 {
        versions.push(&rustls::version::TLS13);
    }
    if t.min_version <= Version::Tls12 && tls12 {
        versions.push(&rustls::version::TLS12);
    }
    let whole = &t.cert.1;
    if versions.is_empty() {
        return Err(at_error(
            file,
            whole,
            "no TLS version left: max_version TLS12 with only TLS 1.3 cipher suites".into(),
        ));
    }
    let chain = chain(file, &t.cert)?;
    let der = key(file, &t.key)?;
    let certified = CertifiedKey::from_der(chain, der, &provider).map_err(|e| {
        at_error(
            file,
            &t.key.1,
            format!("does not go with {}: {e}", t.cert.1.key),
        )
    })?;
    let builder = ServerConfig::builder_with_provider(provider.clone())
        .with_protocol_versions(&versions)
        .map_err(|e| at_error(file, whole, format!("cannot serve TLS so: {e}")))?;
    let (builder, clients) = client_auth(file, t, builder, &provider)?;
    let mut config =
        builder.with_cert_resolver(Arc::new(SingleCertAndKey::from(Arc::new(certified))));
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    config.ignore_client_order = t.prefer_server_order;
    let names: Vec<&str> = versions
        .iter()
        .rev()
        .map(|v| {
            if v.version == rustls::ProtocolVersion::TLSv1_3 {
                "1.3"
            } else {
                "1.2"
            }
        })
        .collect();
    Ok(WebTls {
        config: Arc::new(config),
        said: format!("TLS {}{clients}", names.join("/")),
    })
}
