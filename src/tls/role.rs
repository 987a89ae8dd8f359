//! The Modbus role of a client certificate (docs/security.md "Roles"): Modbus/TCP
//! Security puts it in a certificate extension, OID 1.3.6.1.4.1.50316.802.1, whose
//! value is an ASN.1 UTF8String. Read with the `x509-cert` crate
//! (docs/architecture.md "Dependencies we kept and why"); fuzzed with hostile DER
//! (`fuzz/fuzz_targets/role.rs`). The certificate has been verified by the TLS stack
//! before it gets here, but nothing below trusts that: any bytes give a value or an
//! error, never a panic.

use x509_cert::der::asn1::Utf8StringRef;
use x509_cert::der::oid::ObjectIdentifier;
use x509_cert::der::Decode;
use x509_cert::Certificate;

/// The Modbus role extension (Modbus/TCP Security, "role-based client authorization").
pub(crate) const ROLE_OID: ObjectIdentifier =
    ObjectIdentifier::new_unwrap("1.3.6.1.4.1.50316.802.1");

/// The longest role accepted: roles are short names (`operator`); anything longer is
/// refused rather than logged and compared at length.
pub const MAX_ROLE: usize = 128;

/// What a client certificate says about its holder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Identity {
    /// The subject's distinguished name as RFC 4514 writes it, last part first
    /// (`O=Plant,CN=operator-1`, as `openssl x509 -subject -nameopt RFC2253` shows it).
    pub(crate) subject: String,
    /// The Modbus role, if the certificate carries one.
    pub role: Option<String>,
}

/// Why a certificate's role cannot be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RoleError {
    /// Not a DER X.509 certificate.
    #[error("not an X.509 certificate: {0}")]
    Certificate(String),
    /// The extension's value is not a DER UTF8String.
    #[error("its Modbus role extension is not an ASN.1 UTF8String")]
    NotUtf8String,
    /// The extension is there twice (RFC 5280 §4.2 allows each extension once).
    #[error("it carries the Modbus role extension twice")]
    Twice,
    /// The role is empty, too long, or holds control characters.
    #[error("its Modbus role is empty, longer than {MAX_ROLE} bytes, or holds control characters")]
    Unusable,
}

/// The subject and the Modbus role of the DER certificate `der`.
pub fn identity(der: &[u8]) -> Result<Identity, RoleError> {
    let cert = Certificate::from_der(der).map_err(|e| RoleError::Certificate(e.to_string()))?;
    let tbs = &cert.tbs_certificate;
    let mut role = None;
    for ext in tbs.extensions.iter().flatten() {
        if ext.extn_id != ROLE_OID {
            continue;
        }
        if role.is_some() {
            return Err(RoleError::Twice);
        }
        let value = Utf8StringRef::from_der(ext.extn_value.as_bytes())
            .map_err(|_| RoleError::NotUtf8String)?;
        let value = value.as_str();
        if value.is_empty() || value.len() > MAX_ROLE || value.chars().any(char::is_control) {
            return Err(RoleError::Unusable);
        }
        role = Some(value.to_owned());
    }
    Ok(Identity {
        subject: tbs.subject.to_string(),
        role,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use x509_cert::der::Encode;

    /// Leaf certificates made with the openssl CLI as docs/security.md shows (EC
    /// P-256, signed by a test CA), each with another role extension.
    const OPERATOR: &[u8] = include_bytes!("testdata/operator.der");
    const NO_ROLE: &[u8] = include_bytes!("testdata/no-role.der");
    /// `ASN1:PRINTABLESTRING:operator`: the right OID, the wrong string type.
    const PRINTABLE: &[u8] = include_bytes!("testdata/printable.der");
    /// `ASN1:UTF8String:` (empty).
    const EMPTY: &[u8] = include_bytes!("testdata/empty.der");

    #[test]
    fn the_role_and_subject_of_certificates_made_with_openssl() {
        let id = identity(OPERATOR).unwrap();
        assert_eq!(id.role.as_deref(), Some("operator"));
        assert_eq!(id.subject, "O=Plant A,CN=operator-1");
        let id = identity(NO_ROLE).unwrap();
        assert_eq!((id.role, id.subject.as_str()), (None, "CN=no-role"));
        assert_eq!(identity(PRINTABLE), Err(RoleError::NotUtf8String));
        assert_eq!(identity(EMPTY), Err(RoleError::Unusable));
    }

    #[test]
    fn a_role_given_twice_is_refused() {
        let mut cert = Certificate::from_der(OPERATOR).unwrap();
        let exts = cert.tbs_certificate.extensions.as_mut().unwrap();
        let role = exts.iter().find(|e| e.extn_id == ROLE_OID).unwrap().clone();
        exts.push(role);
        let der = cert.to_der().unwrap();
        assert_eq!(identity(&der), Err(RoleError::Twice));
    }

    #[test]
    fn hostile_bytes_give_an_error_never_a_panic() {
        for bad in [
            &[][..],
            &[0x30],
            &[0x30, 0x80],
            &[0x30, 0x03, 0x02, 0x01, 0x00],
            &[0xFF; 64],
        ] {
            assert!(
                matches!(identity(bad), Err(RoleError::Certificate(_))),
                "{bad:02X?}"
            );
        }
        // Every prefix of a real certificate, and every single byte changed.
        for n in 0..OPERATOR.len() {
            assert!(identity(&OPERATOR[..n]).is_err(), "a prefix of {n} bytes");
        }
        for i in 0..OPERATOR.len() {
            for flip in [0x01, 0x80, 0xFF] {
                let mut c = OPERATOR.to_vec();
                c[i] ^= flip;
                let _ = identity(&c);
            }
        }
    }
}
