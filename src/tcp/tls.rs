//! Modbus/TCP Security (`server.listen_tls`, the spec's port 802): Modbus TCP inside TLS 1.2 or
//! 1.3 (rustls, its default cipher suites), with mutual authentication. The master's certificate
//! must chain to `server.tls.client_ca`; its role, the RoleOID extension
//! (1.3.6.1.4.1.50316.802.1, a UTF8String), decides through `server.tls.roles` what it may ask.
//! Reads the PEM files `[server.tls]` names ([`TlsServer::load`], every problem named by its
//! key) and inspects certificates; knows nothing of sessions or buses.

use crate::config::{self, ConfigError, ConfigErrors, RoleAccess, OTHER_ROLE};
use crate::dispatch::Rights;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use rustls::server::WebPkiClientVerifier;
use rustls::{RootCertStore, ServerConfig};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio_rustls::TlsAcceptor;
use x509_parser::asn1_rs::FromDer;
use x509_parser::certificate::X509Certificate;

/// The RoleOID of the MODBUS/TCP Security specification.
pub(crate) const ROLE_OID: &str = "1.3.6.1.4.1.50316.802.1";

/// A server certificate expiring within this many days is warned about.
pub(crate) const EXPIRY_WARNING_DAYS: i64 = 30;

/// The server side of the TLS listeners, as one reading of `[server.tls]` made it: new
/// connections take the one in force when they are accepted, and keep it.
pub(crate) struct TlsServer {
    pub acceptor: TlsAcceptor,
    roles: BTreeMap<String, RoleAccess>,
    default_access: RoleAccess,
    pub handshake_timeout: Duration,
    /// What `check-config` and the logs say of the server's certificate.
    pub certificate: CertificateInfo,
}

/// The server's certificate chain as an operator needs to know it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct CertificateInfo {
    /// The subject of the server's own certificate, as `CN=gateway, O=Plant`.
    pub subject: String,
    /// When the first certificate of the chain to expire does.
    pub expires: SystemTime,
    /// How many CA certificates `client_ca` holds.
    pub client_cas: usize,
}

impl std::fmt::Debug for TlsServer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TlsServer")
            .field("roles", &self.roles)
            .field("default_access", &self.default_access)
            .field("certificate", &self.certificate)
            .finish_non_exhaustive()
    }
}

impl CertificateInfo {
    /// What to warn an operator of at `now`: a certificate expired, or expiring within
    /// [`EXPIRY_WARNING_DAYS`].
    pub(crate) fn expiry_warning(&self, now: SystemTime) -> Option<String> {
        let days = self.days_left(now);
        if days < 0 {
            Some(format!(
                "the server certificate expired {} days ago: masters will refuse it",
                -days
            ))
        } else if days < EXPIRY_WARNING_DAYS {
            Some(format!(
                "the server certificate expires in {days} days: renew it before masters refuse it"
            ))
        } else {
            None
        }
    }

    /// Whole days from `now` to the expiry; negative once expired.
    pub(crate) fn days_left(&self, now: SystemTime) -> i64 {
        let seconds = match self.expires.duration_since(now) {
            Ok(left) => i64::try_from(left.as_secs()).unwrap_or(i64::MAX),
            Err(past) => -i64::try_from(past.duration().as_secs()).unwrap_or(i64::MAX),
        };
        seconds.div_euclid(86_400)
    }
}

/// Who a master is, from its verified certificate.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Identity {
    /// The `role` label: the role when `server.tls.roles` names it, else `other`.
    pub role_label: String,
    /// The role the certificate carries, if any, as written.
    pub role: Option<String>,
    pub rights: Rights,
    pub subject: String,
}

/// The problems found so far, each with its key.
#[derive(Default)]
struct Problems(Vec<ConfigError>);

impl Problems {
    fn fail(&mut self, key: &str, reason: impl Into<String>) {
        self.0.push(ConfigError {
            key: format!("server.tls.{key}"),
            reason: reason.into(),
        });
    }
}

/// The certificates of a PEM file, or why there are none.
fn read_certificates(path: &Path) -> Result<Vec<CertificateDer<'static>>, String> {
    let pem = read(path)?;
    let certificates = CertificateDer::pem_slice_iter(&pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("{}: not a PEM file of certificates: {e}", path.display()))?;
    if certificates.is_empty() {
        return Err(format!(
            "{}: holds no PEM certificate (-----BEGIN CERTIFICATE-----)",
            path.display()
        ));
    }
    Ok(certificates)
}

fn read(path: &Path) -> Result<Vec<u8>, String> {
    std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))
}

fn parse(der: &[u8]) -> Result<X509Certificate<'_>, String> {
    x509_parser::parse_x509_certificate(der)
        .map(|(_, certificate)| certificate)
        .map_err(|e| format!("not an X.509 certificate: {e}"))
}

fn unix_time(seconds: i64) -> SystemTime {
    match u64::try_from(seconds) {
        Ok(after) => UNIX_EPOCH + Duration::from_secs(after),
        Err(_) => UNIX_EPOCH - Duration::from_secs(seconds.unsigned_abs()),
    }
}

/// The subject and earliest expiry of a chain.
fn inspect_chain(
    path: &Path,
    chain: &[CertificateDer<'_>],
) -> Result<(String, SystemTime), String> {
    let mut subject = String::new();
    let mut expires = None::<SystemTime>;
    for (i, der) in chain.iter().enumerate() {
        let certificate = parse(der).map_err(|e| format!("{}: {e}", path.display()))?;
        if i == 0 {
            subject = certificate.subject().to_string();
        }
        let not_after = unix_time(certificate.validity().not_after.timestamp());
        expires = Some(expires.map_or(not_after, |earliest| earliest.min(not_after)));
    }
    Ok((subject, expires.unwrap_or(UNIX_EPOCH)))
}

impl TlsServer {
    /// Read the files `settings` names and build the TLS server; every problem comes back with
    /// its key: a file that cannot be read or parsed, a key that does not match the
    /// certificate, a CA bundle that verifies nothing.
    pub(crate) fn load(settings: &config::Tls) -> Result<TlsServer, ConfigErrors> {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut problems = Problems::default();
        let chain = read_certificates(&settings.certificate)
            .and_then(|chain| Ok((inspect_chain(&settings.certificate, &chain)?, chain)))
            .map_err(|e| problems.fail("certificate", e))
            .ok();
        let key = read(&settings.private_key)
            .and_then(|pem| {
                PrivateKeyDer::from_pem_slice(&pem).map_err(|e| {
                    format!(
                        "{}: holds no PEM private key (PKCS#8, PKCS#1 or SEC1): {e}",
                        settings.private_key.display()
                    )
                })
            })
            .map_err(|e| problems.fail("private_key", e))
            .ok();
        let verifier = read_certificates(&settings.client_ca)
            .and_then(|cas| {
                let count = cas.len();
                let mut roots = RootCertStore::empty();
                let (_, unusable) = roots.add_parsable_certificates(cas);
                if unusable > 0 {
                    return Err(format!(
                        "{}: {unusable} of its {count} certificates cannot be a CA",
                        settings.client_ca.display()
                    ));
                }
                WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider.clone())
                    .build()
                    .map(|verifier| (verifier, count))
                    .map_err(|e| format!("{}: {e}", settings.client_ca.display()))
            })
            .map_err(|e| problems.fail("client_ca", e))
            .ok();
        let (Some((certificate, chain)), Some(key), Some((verifier, client_cas))) =
            (chain, key, verifier)
        else {
            return Err(ConfigErrors(problems.0));
        };
        let server = ServerConfig::builder_with_provider(provider)
            .with_protocol_versions(&[&rustls::version::TLS13, &rustls::version::TLS12])
            .map_err(|e| ConfigErrors::one("server.tls", e))?
            .with_client_cert_verifier(verifier)
            .with_single_cert(chain, key)
            .map_err(|e| match e {
                rustls::Error::InconsistentKeys(_) => ConfigErrors::one(
                    "server.tls.private_key",
                    format!(
                        "{} is not the key of the certificate in {}",
                        settings.private_key.display(),
                        settings.certificate.display()
                    ),
                ),
                e => ConfigErrors::one(
                    "server.tls.private_key",
                    format!("{}: cannot be used: {e}", settings.private_key.display()),
                ),
            })?;
        let (subject, expires) = certificate;
        Ok(TlsServer {
            acceptor: TlsAcceptor::from(Arc::new(server)),
            roles: settings.roles.clone(),
            default_access: settings.default_role_access,
            handshake_timeout: settings.handshake_timeout,
            certificate: CertificateInfo {
                subject,
                expires,
                client_cas,
            },
        })
    }

    /// Who the master with this verified certificate chain is, and what its role allows.
    pub(crate) fn identify(&self, chain: Option<&[CertificateDer<'_>]>) -> Identity {
        let end_entity = chain.and_then(<[_]>::first).map(|der| parse(der));
        let (role, subject) = match &end_entity {
            Some(Ok(certificate)) => (role_of(certificate), certificate.subject().to_string()),
            _ => (None, String::new()),
        };
        let listed = role
            .as_ref()
            .and_then(|name| self.roles.get_key_value(name));
        let (role_label, access) = match listed {
            Some((name, access)) => (name.clone(), *access),
            None => (OTHER_ROLE.to_owned(), self.default_access),
        };
        Identity {
            role_label,
            role,
            rights: rights(access),
            subject,
        }
    }
}

fn rights(access: RoleAccess) -> Rights {
    match access {
        RoleAccess::ReadWrite => Rights::ReadWrite,
        RoleAccess::ReadOnly => Rights::ReadOnly,
        RoleAccess::None => Rights::NoAccess,
    }
}

/// The role in a certificate's RoleOID extension; `None` without one, or when it is not the
/// UTF8String the spec says it is.
pub(crate) fn role_of(certificate: &X509Certificate<'_>) -> Option<String> {
    let extension = certificate
        .extensions()
        .iter()
        .find(|extension| extension.oid.to_id_string() == ROLE_OID)?;
    let (_, role) = String::from_der(extension.value).ok()?;
    Some(role)
}
