//! A Modbus/TCP Security listener (docs/security.md): every master presents a client
//! certificate that chains to `client_ca` (rustls' WebPKI verifier: signature, validity
//! dates, key usage), its Modbus role is read during the handshake and must name a
//! `[[role]]` (or the listener's `default_role` stands for a certificate without one),
//! else the handshake fails with the alert `access_denied`. The handshake runs in the
//! connection's own task, bounded by `handshake_timeout_ms` and by the listener's
//! handshake budget (`tcp/accept/handshakes.rs`): a peer that stalls holds no connection slot.
//!
//! The certificate and key (and the CA) are read again on SIGHUP: new connections get
//! the new ones, connected masters keep their session. Sessions are never resumed, so
//! every connection is verified against the CA in force and its role read afresh.

use super::role::{identity, RoleError};
use super::{certified_key, provider, roots, TlsError, VERSIONS};
use crate::access::Policy;
use crate::config::{AccessRole, TlsListen};
use rustls::client::danger::HandshakeSignatureValid;
use rustls::crypto::CryptoProvider;
use rustls::pki_types::{CertificateDer, UnixTime};
use rustls::server::danger::{ClientCertVerified, ClientCertVerifier};
use rustls::server::{NoServerSessionStorage, WebPkiClientVerifier};
use rustls::sign::{CertifiedKey, SingleCertAndKey};
use rustls::{CertificateError, DigitallySignedStruct, DistinguishedName, SignatureScheme};
use std::sync::{Arc, Mutex, RwLock};
use std::time::Duration;
use tokio::net::TcpStream;
use tokio_rustls::server::TlsStream;
use tokio_rustls::TlsAcceptor;

/// What a listener's files give: the verifier of client certificates and the
/// gateway's certificate with its key.
#[derive(Debug)]
pub(crate) struct Material {
    provider: Arc<CryptoProvider>,
    verifier: Arc<dyn ClientCertVerifier>,
    key: Arc<CertifiedKey>,
}

impl Material {
    /// Reads the files of `t`; `prefix` is what errors call the table
    /// (`listen[0].tls`).
    pub(crate) fn load(t: &TlsListen, prefix: &str) -> Result<Material, TlsError> {
        let provider = provider();
        let ca_key = format!("{prefix}.client_ca");
        let roots = roots(&ca_key, &t.client_ca)?;
        let verifier = WebPkiClientVerifier::builder_with_provider(roots, provider.clone())
            .build()
            .map_err(|e| {
                super::error(
                    &ca_key,
                    &t.client_ca,
                    format!("cannot verify clients with it: {e}"),
                )
            })?;
        let key = certified_key(
            (&format!("{prefix}.cert"), &t.cert),
            (&format!("{prefix}.key"), &t.key),
            &provider,
        )?;
        Ok(Material {
            provider,
            verifier,
            key,
        })
    }

    /// The gateway's certificate's subject, for the log.
    fn subject(&self) -> String {
        self.key
            .cert
            .first()
            .and_then(|c| identity(c).ok())
            .map_or_else(|| "?".into(), |id| id.subject)
    }
}

/// A master admitted: its role and what it may do, and who its certificate says it is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Grant {
    pub(crate) role: String,
    pub(crate) policy: Policy,
    /// The certificate's subject, RFC 4514.
    pub(crate) subject: String,
    /// The certificate carried no role: `default_role` stands for it.
    pub(crate) defaulted: bool,
}

/// Why a certificate that chains to the CA was refused anyway.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum RoleRefused {
    /// No role, and the listener has no `default_role`.
    NoRole { subject: String },
    /// A role no `[[role]]` names.
    Unknown { subject: String, role: String },
    /// The role extension cannot be read.
    Malformed(RoleError),
}

impl std::fmt::Display for RoleRefused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RoleRefused::NoRole { subject } => write!(
                f,
                "the certificate of {subject:?} carries no Modbus role and the listener has no default_role"
            ),
            RoleRefused::Unknown { subject, role } => write!(
                f,
                "the certificate of {subject:?} carries the role {role:?}, which no [[role]] names"
            ),
            RoleRefused::Malformed(e) => write!(f, "the certificate is refused: {e}"),
        }
    }
}

/// Why a TLS connection ended before it carried a request.
#[derive(Debug)]
pub(crate) enum Refused {
    /// The handshake took longer than `handshake_timeout_ms`.
    TimedOut(Duration),
    /// The handshake failed (what rustls said: an unknown CA, an expired
    /// certificate, no certificate, a protocol version it does not speak...).
    Handshake(String),
    /// The certificate is good but its role is not.
    Role(RoleRefused),
}

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refused::TimedOut(d) => write!(f, "no TLS handshake within {} ms", d.as_millis()),
            Refused::Handshake(e) => write!(f, "TLS handshake failed: {e}"),
            Refused::Role(r) => write!(f, "{r}"),
        }
    }
}

/// The role a certificate gets on a listener (or a dial) with `roles` and
/// `default_role`.
pub(crate) fn grant(
    der: &[u8],
    roles: &[AccessRole],
    default_role: Option<&str>,
) -> Result<Grant, RoleRefused> {
    let id = identity(der).map_err(RoleRefused::Malformed)?;
    let (name, defaulted) = match (id.role, default_role) {
        (Some(r), _) => (r, false),
        (None, Some(d)) => (d.to_owned(), true),
        (None, None) => {
            return Err(RoleRefused::NoRole {
                subject: id.subject,
            })
        }
    };
    match roles.iter().find(|r| r.name == name) {
        Some(r) => Ok(Grant {
            role: name,
            policy: r.policy.clone(),
            subject: id.subject,
            defaulted,
        }),
        None => Err(RoleRefused::Unknown {
            subject: id.subject,
            role: name,
        }),
    }
}

/// The WebPKI verifier, then the role: one per connection, so the role it read is this
/// connection's.
#[derive(Debug)]
struct RoleCheck {
    inner: Arc<dyn ClientCertVerifier>,
    roles: Arc<[AccessRole]>,
    default_role: Option<String>,
    outcome: Mutex<Option<Result<Grant, RoleRefused>>>,
}

impl ClientCertVerifier for RoleCheck {
    fn offer_client_auth(&self) -> bool {
        true
    }

    fn client_auth_mandatory(&self) -> bool {
        true
    }

    fn root_hint_subjects(&self) -> &[DistinguishedName] {
        self.inner.root_hint_subjects()
    }

    fn verify_client_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        intermediates: &[CertificateDer<'_>],
        now: UnixTime,
    ) -> Result<ClientCertVerified, rustls::Error> {
        self.inner
            .verify_client_cert(end_entity, intermediates, now)?;
        let outcome = grant(end_entity, &self.roles, self.default_role.as_deref());
        let ok = outcome.is_ok();
        *self.outcome.lock().expect("not poisoned") = Some(outcome);
        if ok {
            Ok(ClientCertVerified::assertion())
        } else {
            let e = CertificateError::ApplicationVerificationFailure;
            Err(rustls::Error::InvalidCertificate(e))
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        self.inner.verify_tls12_signature(message, cert, dss)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        self.inner.verify_tls13_signature(message, cert, dss)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.inner.supported_verify_schemes()
    }
}

/// One TLS listener: its settings, its roles, and the files as last (re)loaded.
#[derive(Debug)]
pub(crate) struct Acceptor {
    settings: TlsListen,
    /// What errors and the log call it: `listen[0].tls`.
    prefix: String,
    roles: Arc<[AccessRole]>,
    material: RwLock<Arc<Material>>,
}

impl Acceptor {
    /// Loads the files of `settings`.
    pub(crate) fn new(
        settings: &TlsListen,
        prefix: &str,
        roles: &[AccessRole],
    ) -> Result<Acceptor, TlsError> {
        let material = Material::load(settings, prefix)?;
        Ok(Acceptor {
            settings: settings.clone(),
            prefix: prefix.to_owned(),
            roles: roles.into(),
            material: RwLock::new(Arc::new(material)),
        })
    }

    /// Reads the files again; on success new connections use them (connected masters
    /// keep their session), else nothing changes. Returns the new certificate's subject.
    pub(crate) fn reload(&self) -> Result<String, TlsError> {
        let material = Material::load(&self.settings, &self.prefix)?;
        let subject = material.subject();
        *self.material.write().expect("not poisoned") = Arc::new(material);
        Ok(subject)
    }

    /// What the log calls this listener's TLS table.
    pub(crate) fn name(&self) -> &str {
        &self.prefix
    }

    /// The handshake on `stream`, bounded by `handshake_timeout_ms`, and the master's
    /// role.
    pub(crate) async fn accept(
        &self,
        stream: TcpStream,
    ) -> Result<(TlsStream<TcpStream>, Grant), Refused> {
        let material = self.material.read().expect("not poisoned").clone();
        let check = Arc::new(RoleCheck {
            inner: material.verifier.clone(),
            roles: self.roles.clone(),
            default_role: self.settings.default_role.clone(),
            outcome: Mutex::new(None),
        });
        let mut config = rustls::ServerConfig::builder_with_provider(material.provider.clone())
            .with_protocol_versions(VERSIONS)
            .expect("the ring provider speaks TLS 1.2 and 1.3")
            .with_client_cert_verifier(check.clone())
            .with_cert_resolver(Arc::new(SingleCertAndKey::from(material.key.clone())));
        // No resumption: every connection shows its certificate to the CA in force.
        config.session_storage = Arc::new(NoServerSessionStorage {});
        config.send_tls13_tickets = 0;
        let within = Duration::from_millis(self.settings.handshake_timeout_ms);
        let handshake = TlsAcceptor::from(Arc::new(config)).accept(stream);
        let result = tokio::time::timeout(within, handshake).await;
        let outcome = check.outcome.lock().expect("not poisoned").take();
        match (result, outcome) {
            (Err(_), _) => Err(Refused::TimedOut(within)),
            (Ok(Err(_)), Some(Err(role))) => Err(Refused::Role(role)),
            (Ok(Err(e)), _) => Err(Refused::Handshake(e.to_string())),
            (Ok(Ok(stream)), Some(Ok(grant))) => Ok((stream, grant)),
            (Ok(Ok(_)), _) => Err(Refused::Handshake(
                "no client certificate was verified".into(),
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const OPERATOR: &[u8] = include_bytes!("testdata/operator.der");
    const NO_ROLE: &[u8] = include_bytes!("testdata/no-role.der");

    fn role(name: &str, read_only: bool) -> AccessRole {
        AccessRole {
            name: name.into(),
            policy: Policy {
                read_only,
                write: vec![],
            },
            priority: None,
        }
    }

    #[test]
    fn a_role_must_name_a_role_table_and_the_default_stands_for_none() {
        let roles = [role("operator", false), role("viewer", true)];
        let g = grant(OPERATOR, &roles, None).unwrap();
        assert_eq!(
            (g.role.as_str(), g.defaulted, g.policy.read_only),
            ("operator", false, false)
        );
        assert_eq!(
            grant(NO_ROLE, &roles, None),
            Err(RoleRefused::NoRole {
                subject: "CN=no-role".into()
            })
        );
        let g = grant(NO_ROLE, &roles, Some("viewer")).unwrap();
        assert_eq!(
            (g.role.as_str(), g.defaulted, g.policy.read_only),
            ("viewer", true, true)
        );
        let only_viewer = [role("viewer", true)];
        let e = grant(OPERATOR, &only_viewer, Some("viewer")).unwrap_err();
        assert_eq!(
            e.to_string(),
            "the certificate of \"O=Plant A,CN=operator-1\" carries the role \"operator\", which no [[role]] names"
        );
    }
}
