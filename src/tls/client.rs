//! The gateway as a TLS client of a device on the network (`[[line]]` with `tcp = {
//! address, tls = { cert, key, device_ca, server_name } }`, docs/security.md): the
//! device's certificate must chain to `device_ca` and carry `server_name` (by default
//! the host of `address`, a DNS name or an IP address); mbgate presents its own
//! certificate. The files are read at each connect, so a renewed certificate is used
//! from the next reconnect on.

use super::{certified_key, provider, roots, TlsError, VERSIONS};
use crate::config::TlsDevice;
use rustls::pki_types::ServerName;
use rustls::sign::SingleCertAndKey;
use std::sync::Arc;
use tokio::net::TcpStream;
use tokio_rustls::client::TlsStream;
use tokio_rustls::TlsConnector;

/// What a connect to a TLS device needs: the client configuration and the name the
/// device's certificate must carry.
#[derive(Debug, Clone)]
pub(crate) struct Connector {
    config: Arc<rustls::ClientConfig>,
    name: ServerName<'static>,
}

/// The host of `host:port` (`[::1]:502` gives `::1`).
fn host(address: &str) -> &str {
    let h = address.rsplit_once(':').map_or(address, |(h, _)| h);
    h.strip_prefix('[')
        .and_then(|h| h.strip_suffix(']'))
        .unwrap_or(h)
}

impl Connector {
    /// Reads the files of `t` for the device at `address`; `prefix` is what errors
    /// call the table (`line[0].tcp.tls`).
    pub(crate) fn load(t: &TlsDevice, address: &str, prefix: &str) -> Result<Connector, TlsError> {
        let provider = provider();
        let roots = roots(&format!("{prefix}.device_ca"), &t.device_ca)?;
        let key = certified_key(
            (&format!("{prefix}.cert"), &t.cert),
            (&format!("{prefix}.key"), &t.key),
            &provider,
        )?;
        let config = rustls::ClientConfig::builder_with_provider(provider)
            .with_protocol_versions(VERSIONS)
            .expect("the ring provider speaks TLS 1.2 and 1.3")
            .with_root_certificates(roots)
            .with_client_cert_resolver(Arc::new(SingleCertAndKey::from(key)));
        let name = t.server_name.as_deref().unwrap_or_else(|| host(address));
        let name = ServerName::try_from(name.to_owned()).map_err(|_| TlsError {
            key: format!("{prefix}.server_name"),
            path: t.device_ca.clone(),
            message: format!("{name:?} is not a DNS name or an IP address: give server_name"),
        })?;
        Ok(Connector {
            config: Arc::new(config),
            name,
        })
    }

    /// The handshake over `stream`.
    pub(crate) async fn connect(&self, stream: TcpStream) -> std::io::Result<TlsStream<TcpStream>> {
        TlsConnector::from(self.config.clone())
            .connect(self.name.clone(), stream)
            .await
    }
}

#[cfg(test)]
mod tests {
    use super::host;

    #[test]
    fn the_host_of_an_address() {
        assert_eq!(host("plc.local:802"), "plc.local");
        assert_eq!(host("10.0.0.5:802"), "10.0.0.5");
        assert_eq!(host("[2001:db8::5]:802"), "2001:db8::5");
    }
}
