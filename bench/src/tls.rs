//! The TLS scenarios' private PKI, made at run time (rcgen): a CA, the gateway's certificate for
//! 127.0.0.1, and one master certificate with a read-only role that every TLS master presents.
//! All ECDSA P-256 (rcgen's default key); the files live in a temp directory removed on drop.

use rcgen::{
    BasicConstraints, CertificateParams, CertifiedIssuer, CustomExtension, DnType,
    ExtendedKeyUsagePurpose, IsCa, KeyPair, KeyUsagePurpose, SanType,
};
use std::net::{IpAddr, Ipv4Addr};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tokio_rustls::rustls;
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};
use tokio_rustls::TlsConnector;

/// The RoleOID of the MODBUS/TCP Security specification, as rcgen takes it.
const ROLE_OID: &[u64] = &[1, 3, 6, 1, 4, 1, 50316, 802, 1];
/// The role of the bench's master certificate, given read-only access in `[server.tls]`.
const ROLE: &str = "bench";

/// The certificates of one scenario: files for the gateway, a connector for the masters.
pub struct Pki {
    dir: PathBuf,
    /// `[server.tls]` for the gateway, naming the files in `dir`.
    pub table: String,
    /// Trusts the CA and presents the master certificate.
    pub connector: TlsConnector,
}

impl Drop for Pki {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn params(name: &str) -> Result<CertificateParams, String> {
    let mut params = CertificateParams::new(Vec::<String>::new()).map_err(|e| e.to_string())?;
    params.distinguished_name.push(DnType::CommonName, name);
    Ok(params)
}

fn key() -> Result<KeyPair, String> {
    KeyPair::generate().map_err(|e| e.to_string())
}

impl Pki {
    /// A new CA, server and master certificate in a fresh directory named after `scenario`.
    pub fn new(scenario: &str) -> Result<Pki, String> {
        let dir =
            std::env::temp_dir().join(format!("mbgw-bench-tls-{}-{scenario}", std::process::id()));
        std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        match certificates(&dir) {
            Ok((table, connector)) => Ok(Pki {
                dir,
                table,
                connector,
            }),
            Err(e) => {
                let _ = std::fs::remove_dir_all(&dir);
                Err(e)
            }
        }
    }
}

/// The certificates written to `dir`: the `[server.tls]` table naming them, and the masters'
/// connector.
fn certificates(dir: &Path) -> Result<(String, TlsConnector), String> {
    let e = |e: rcgen::Error| e.to_string();

    let mut ca = params("modbus-gateway-bench CA")?;
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    let ca = CertifiedIssuer::self_signed(ca, key()?).map_err(e)?;

    let mut server = params("modbus-gateway")?;
    server.subject_alt_names = vec![SanType::IpAddress(IpAddr::V4(Ipv4Addr::LOCALHOST))];
    server.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    server.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth];
    server.use_authority_key_identifier_extension = true;
    let server_key = key()?;
    let server = server.signed_by(&server_key, &ca).map_err(e)?;

    let mut master = params("bench-master")?;
    master.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    master.extended_key_usages = vec![ExtendedKeyUsagePurpose::ClientAuth];
    master.use_authority_key_identifier_extension = true;
    // The RoleOID's value: a DER UTF8String.
    let mut role = vec![0x0C, u8::try_from(ROLE.len()).unwrap_or(0)];
    role.extend_from_slice(ROLE.as_bytes());
    master
        .custom_extensions
        .push(CustomExtension::from_oid_content(ROLE_OID, role));
    let master_key = key()?;
    let master = master.signed_by(&master_key, &ca).map_err(e)?;

    let write = |name: &str, pem: String| -> Result<PathBuf, String> {
        let path = dir.join(name);
        std::fs::write(&path, pem).map_err(|e| format!("{}: {e}", path.display()))?;
        Ok(path)
    };
    let (ca_path, cert_path, key_path) = (
        write("ca.crt", ca.pem())?,
        write("server.crt", server.pem())?,
        write("server.key", server_key.serialize_pem())?,
    );
    let table = format!(
        "[server.tls]\ncertificate = \"{}\"\nprivate_key = \"{}\"\nclient_ca = \"{}\"\n\
             roles = {{ {ROLE} = \"read_only\" }}\n",
        cert_path.display(),
        key_path.display(),
        ca_path.display()
    );

    let mut roots = rustls::RootCertStore::empty();
    roots.add(ca.der().clone()).map_err(|e| e.to_string())?;
    let config = rustls::ClientConfig::builder_with_provider(Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .map_err(|e| e.to_string())?
    .with_root_certificates(roots)
    .with_client_auth_cert(
        vec![CertificateDer::clone(master.der())],
        PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(master_key.serialize_der())),
    )
    .map_err(|e| e.to_string())?;
    Ok((table, TlsConnector::from(Arc::new(config))))
}
