//! A `tls://` device's TLS: the gateway as a Modbus/TCP Security client, with the certificate and
//! key `[bus.tls]` names (which may carry a role the device checks), verifying the device's
//! certificate against `[bus.tls] ca` and the name it must carry (`server_name`, or the device's
//! HOST). Read once when the bus's device is made, so that a bad file is a configuration error
//! naming its key; used at every connect. Knows nothing of Modbus.

use crate::config::DeviceTls;
use crate::pem;
use rustls::pki_types::ServerName;
use rustls::ClientConfig;
use std::io;
use std::sync::Arc;
use tokio::net::TcpStream;
use tokio_rustls::client::TlsStream;
use tokio_rustls::TlsConnector;

/// What a `tls://` device's connections are made with, and the settings it was read from.
#[derive(Clone)]
pub struct TlsDevice {
    settings: DeviceTls,
    connector: TlsConnector,
    name: ServerName<'static>,
}

impl TlsDevice {
    /// Read `settings`' files for a device at `host`; every problem comes back with its key
    /// under `[bus.tls]` (`certificate`, `private_key`, `ca`, `server_name`).
    pub(crate) fn load(
        settings: &DeviceTls,
        host: &str,
    ) -> Result<TlsDevice, Vec<(&'static str, String)>> {
        let mut problems = Vec::new();
        let chain = pem::certificates(&settings.certificate)
            .map_err(|e| problems.push(("certificate", e)))
            .ok();
        let key = pem::private_key(&settings.private_key)
            .map_err(|e| problems.push(("private_key", e)))
            .ok();
        let roots = pem::roots(&settings.ca)
            .map_err(|e| problems.push(("ca", e)))
            .ok();
        let wanted = settings.server_name.as_deref().unwrap_or(host);
        let name = ServerName::try_from(wanted.to_owned())
            .map_err(|e| problems.push(("server_name", format!("`{wanted}`: {e}"))))
            .ok();
        let (Some(chain), Some(key), Some(roots), Some(name)) = (chain, key, roots, name) else {
            return Err(problems);
        };
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let config = ClientConfig::builder_with_provider(provider)
            .with_protocol_versions(&[&rustls::version::TLS13, &rustls::version::TLS12])
            .map_err(|e| vec![("certificate", e.to_string())])?
            .with_root_certificates(roots)
            .with_client_auth_cert(chain, key)
            .map_err(|e| vec![("private_key", format!("does not fit the certificate: {e}"))])?;
        Ok(TlsDevice {
            settings: settings.clone(),
            connector: TlsConnector::from(Arc::new(config)),
            name,
        })
    }

    /// Whether `other` was read from the same settings.
    pub(super) fn same_as(&self, other: &TlsDevice) -> bool {
        self.settings == other.settings
    }

    /// The handshake on a connected `stream`: the device's certificate must chain to `ca` and
    /// carry the name.
    pub(super) async fn handshake(&self, stream: TcpStream) -> io::Result<TlsStream<TcpStream>> {
        self.connector.connect(self.name.clone(), stream).await
    }
}
