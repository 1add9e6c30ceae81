//! A private PKI made at test time (rcgen): a CA, server certificates for 127.0.0.1, master
//! certificates with or without the Modbus RoleOID, and a TLS master (rustls) that presents one.

use crate::master::{connect_from, RawMaster};
use crate::wait::within;
use rcgen::{
    BasicConstraints, CertificateParams, CertificateRevocationListParams, CertifiedIssuer,
    CustomExtension, DnType, ExtendedKeyUsagePurpose, IsCa, KeyIdMethod, KeyPair, KeyUsagePurpose,
    RevocationReason, RevokedCertParams, SanType, SerialNumber,
};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, SystemTime};
use tokio::net::TcpStream;
use tokio_rustls::client::TlsStream;
use tokio_rustls::TlsConnector;

/// The RoleOID of the MODBUS/TCP Security specification, as rcgen takes it.
const ROLE_OID: &[u64] = &[1, 3, 6, 1, 4, 1, 50316, 802, 1];
static DIRS: AtomicUsize = AtomicUsize::new(0);
/// Serial numbers of the certificates issued, so that a CRL can name them.
static SERIALS: AtomicU64 = AtomicU64::new(1000);

/// A certificate and its key, as PEM, and where they were written.
pub struct Issued {
    pub serial: u64,
    pub cert_pem: String,
    pub key_pem: String,
    pub cert_path: PathBuf,
    pub key_path: PathBuf,
}

impl Issued {
    pub fn der(&self) -> CertificateDer<'static> {
        CertificateDer::from_pem_slice(self.cert_pem.as_bytes()).expect("a PEM certificate")
    }
}

/// A CA with its directory of files; removed when dropped.
pub struct Pki {
    pub dir: PathBuf,
    ca: CertifiedIssuer<'static, KeyPair>,
    pub ca_path: PathBuf,
}

impl Drop for Pki {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// What a master certificate carries.
#[derive(Clone, Copy)]
pub enum Role<'a> {
    /// No RoleOID extension.
    Without,
    /// The RoleOID as the spec says: a UTF8String.
    Named(&'a str),
}

/// `text` as a DER UTF8String, the RoleOID's value.
fn utf8_string(text: &str) -> Vec<u8> {
    let mut der = vec![0x0C, u8::try_from(text.len()).expect("a short role")];
    der.extend_from_slice(text.as_bytes());
    der
}

fn params(name: &str, days: (i64, i64)) -> CertificateParams {
    let mut params = CertificateParams::new(Vec::<String>::new()).expect("params");
    params.distinguished_name.push(DnType::CommonName, name);
    let now = time::OffsetDateTime::now_utc();
    params.not_before = now + time::Duration::days(days.0);
    params.not_after = now + time::Duration::days(days.1);
    params
}

impl Pki {
    /// A new CA named `name`, its certificate in `{name}.crt` of a fresh temporary directory.
    pub fn new(name: &str) -> Pki {
        let dir = std::env::temp_dir().join(format!(
            "mbgw-tls-{}-{}",
            std::process::id(),
            DIRS.fetch_add(1, Ordering::Relaxed)
        ));
        Pki::in_dir(dir, name)
    }

    /// A new CA named `name`, its certificate in `{name}.crt` of `dir`, which is created now and
    /// removed with everything in it when the PKI is dropped.
    pub fn in_dir(dir: PathBuf, name: &str) -> Pki {
        std::fs::create_dir_all(&dir).expect("temp dir");
        let mut params = params(name, (-1, 3650));
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        let ca = CertifiedIssuer::self_signed(params, KeyPair::generate().expect("key"))
            .expect("CA certificate");
        let ca_path = dir.join(format!("{name}.crt"));
        std::fs::write(&ca_path, ca.pem()).expect("write CA");
        Pki { dir, ca, ca_path }
    }

    fn issue(&self, file: &str, mut params: CertificateParams) -> Issued {
        let key = KeyPair::generate().expect("key");
        params.use_authority_key_identifier_extension = true;
        let serial = SERIALS.fetch_add(1, Ordering::Relaxed);
        params.serial_number = Some(SerialNumber::from(serial));
        let cert = params.signed_by(&key, &self.ca).expect("signed");
        let issued = Issued {
            serial,
            cert_pem: cert.pem(),
            key_pem: key.serialize_pem(),
            cert_path: self.dir.join(format!("{file}.crt")),
            key_path: self.dir.join(format!("{file}.key")),
        };
        std::fs::write(&issued.cert_path, &issued.cert_pem).expect("write certificate");
        std::fs::write(&issued.key_path, &issued.key_pem).expect("write key");
        issued
    }

    /// A server certificate for 127.0.0.1 and localhost, valid from a day ago for `days`.
    pub fn server(&self, file: &str, name: &str, days: i64) -> Issued {
        let mut params = params(name, (-1, days));
        params.subject_alt_names = vec![
            SanType::DnsName("localhost".try_into().expect("name")),
            SanType::IpAddress(IpAddr::V4(Ipv4Addr::LOCALHOST)),
        ];
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth];
        self.issue(file, params)
    }

    /// A master certificate valid over `days` (from, to) around now, with `role`.
    pub fn master_valid(&self, file: &str, role: Role<'_>, days: (i64, i64)) -> Issued {
        let mut params = params(file, days);
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ClientAuth];
        if let Role::Named(role) = role {
            params
                .custom_extensions
                .push(CustomExtension::from_oid_content(
                    ROLE_OID,
                    utf8_string(role),
                ));
        }
        self.issue(file, params)
    }

    /// A master certificate valid for a year, with `role`.
    pub fn master(&self, file: &str, role: Role<'_>) -> Issued {
        self.master_valid(file, role, (-1, 365))
    }

    /// A CRL of this CA revoking `revoked`, written to `file` (PEM).
    pub fn crl(&self, file: &str, revoked: &[&Issued]) -> PathBuf {
        let now = time::OffsetDateTime::now_utc();
        let params = CertificateRevocationListParams {
            this_update: now - time::Duration::hours(1),
            next_update: now + time::Duration::days(7),
            crl_number: SerialNumber::from(1u64),
            issuing_distribution_point: None,
            revoked_certs: revoked
                .iter()
                .map(|issued| RevokedCertParams {
                    serial_number: SerialNumber::from(issued.serial),
                    revocation_time: now - time::Duration::minutes(5),
                    reason_code: Some(RevocationReason::KeyCompromise),
                    invalidity_date: None,
                })
                .collect(),
            key_identifier_method: KeyIdMethod::Sha256,
        };
        let crl = params.signed_by(&self.ca).expect("a CRL");
        let path = self.dir.join(file);
        std::fs::write(&path, crl.pem().expect("PEM")).expect("write CRL");
        path
    }

    /// The `[server.tls]` table for `server`, trusting this CA, with `extra` keys.
    pub fn tls_table(&self, server: &Issued, extra: &str) -> String {
        format!(
            "[server.tls]\ncertificate = \"{}\"\nprivate_key = \"{}\"\nclient_ca = \"{}\"\n{extra}\n",
            server.cert_path.display(),
            server.key_path.display(),
            self.ca_path.display()
        )
    }

    /// A TLS client that trusts this CA and presents `master` (or no certificate).
    pub fn connector(&self, master: Option<&Issued>) -> TlsConnector {
        connector(&self.ca_path, master)
    }
}

/// A TLS client that trusts the CAs of `ca_path` and presents `master` (or no certificate).
pub fn connector(ca_path: &Path, master: Option<&Issued>) -> TlsConnector {
    connector_with(ca_path, master, rustls::DEFAULT_VERSIONS)
}

/// [`connector`] speaking only the TLS `versions` given.
pub fn connector_with(
    ca_path: &Path,
    master: Option<&Issued>,
    versions: &[&'static rustls::SupportedProtocolVersion],
) -> TlsConnector {
    let mut roots = rustls::RootCertStore::empty();
    for ca in CertificateDer::pem_file_iter(ca_path).expect("CA file") {
        roots.add(ca.expect("CA")).expect("a CA");
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(versions)
        .expect("versions")
        .with_root_certificates(roots);
    let config = match master {
        Some(master) => builder
            .with_client_auth_cert(
                vec![master.der()],
                PrivateKeyDer::from_pem_slice(master.key_pem.as_bytes()).expect("key"),
            )
            .expect("client certificate"),
        None => builder.with_no_client_auth(),
    };
    TlsConnector::from(Arc::new(config))
}

/// A TLS session with the gateway at `addr`; the error if the handshake fails on this side.
pub async fn tls_connect(
    addr: SocketAddr,
    connector: &TlsConnector,
) -> std::io::Result<TlsStream<TcpStream>> {
    let tcp = within("connect", TcpStream::connect(addr)).await?;
    tls_handshake(tcp, addr, connector).await
}

/// [`tls_connect`] from the loopback address `source` (127.0.0.x).
pub async fn tls_connect_from(
    source: [u8; 4],
    addr: SocketAddr,
    connector: &TlsConnector,
) -> std::io::Result<TlsStream<TcpStream>> {
    tls_handshake(connect_from(source, addr).await, addr, connector).await
}

async fn tls_handshake(
    tcp: TcpStream,
    addr: SocketAddr,
    connector: &TlsConnector,
) -> std::io::Result<TlsStream<TcpStream>> {
    let name = ServerName::IpAddress(addr.ip().into());
    within("TLS handshake", connector.connect(name, tcp)).await
}

/// A master on a TLS session with the gateway at `addr`, presenting `master`.
pub async fn tls_master(addr: SocketAddr, connector: &TlsConnector) -> RawMaster {
    RawMaster::over(tls_connect(addr, connector).await.expect("TLS handshake"))
}

/// Unix time `days` from now, to the second, for comparing with the expiry gauge.
pub fn days_from_now(days: i64) -> f64 {
    let now = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap_or(Duration::ZERO);
    now.as_secs_f64() + days as f64 * 86_400.0
}
