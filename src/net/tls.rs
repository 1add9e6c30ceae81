//! Modbus/TCP Security (`server.listen_tls`, the spec's port 802): Modbus TCP inside TLS 1.2 or
//! 1.3 (rustls, its default cipher suites), with mutual authentication. The master's certificate
//! must chain to `server.tls.client_ca`; its role, the RoleOID extension
//! (1.3.6.1.4.1.50316.802.1, a UTF8String), decides through `server.tls.roles` what it may ask.
//! Reads the PEM files `[server.tls]` names ([`TlsServer::load`], every problem named by its
//! key) and inspects certificates; knows nothing of sessions or buses.

use crate::config::{self, ConfigError, ConfigErrors, Role, RoleAccess, UnitSet, OTHER_ROLE};
use crate::master::Rights;
use crate::pem;
use rustls::pki_types::{CertificateDer, CertificateRevocationListDer};
use rustls::server::danger::ClientCertVerifier;
use rustls::server::{VerifierBuilderError, WebPkiClientVerifier};
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
pub(crate) const EXPIRY_WARNING_DAYS: u64 = 30;

/// The server side of the TLS listeners, as one reading of `[server.tls]` made it: new
/// connections take the one in force when they are accepted, and keep it.
pub(crate) struct TlsServer {
    pub(crate) acceptor: TlsAcceptor,
    roles: BTreeMap<String, Role>,
    default_access: RoleAccess,
    pub handshake_timeout: Duration,
    /// What `check-config` and the logs say of the server's certificate.
    pub certificate: CertificateInfo,
}

/// The server's certificate chain as an operator needs to know it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct CertificateInfo {
    /// The subject of the server's own certificate, as `CN=gateway, O=Plant`.
    pub(crate) subject: String,
    /// When the first certificate of the chain to expire does.
    pub expires: SystemTime,
    /// How many CA certificates `client_ca` holds.
    pub(crate) client_cas: usize,
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
    /// Whole days left at `now`, or `Err` with the whole days since it expired.
    pub(crate) fn days_left(&self, now: SystemTime) -> Result<u64, u64> {
        const DAY: u64 = 86_400;
        match self.expires.duration_since(now) {
            Ok(left) if !left.is_zero() => Ok(left.as_secs() / DAY),
            Ok(_) => Err(0),
            Err(past) => Err(past.duration().as_secs() / DAY),
        }
    }

    /// When it expires, as `check-config` says it: "in 364 days" or "7 days ago".
    pub(crate) fn expiry(&self, now: SystemTime) -> String {
        match self.days_left(now) {
            Ok(days) => format!("in {days} days"),
            Err(days) => format!("{days} days ago"),
        }
    }

    /// What to warn an operator of at `now`: a certificate expired, or expiring within
    /// [`EXPIRY_WARNING_DAYS`].
    pub(crate) fn expiry_warning(&self, now: SystemTime) -> Option<String> {
        match self.days_left(now) {
            Err(days) => Some(format!(
                "the server certificate expired {days} days ago: masters will refuse it"
            )),
            Ok(days) if days < EXPIRY_WARNING_DAYS => Some(format!(
                "the server certificate expires in {days} days: renew it before masters refuse it"
            )),
            Ok(_) => None,
        }
    }
}

/// Who a master is, from its verified certificate.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Certified {
    /// The `role` label: the role when `server.tls.roles` names it, else `other`.
    pub(crate) role_label: String,
    /// The role the certificate carries, if any, as written.
    pub role: Option<String>,
    /// Why a RoleOID extension the certificate has was not read as a role.
    pub(crate) role_problem: Option<&'static str>,
    pub rights: Rights,
    /// The unit ids its role may address; `None`: any.
    pub units: Option<UnitSet>,
    pub(crate) subject: String,
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

/// A problem with the key it is about: `("client_ca", "...")`.
type KeyedProblem = (&'static str, String);

/// What checks a master's certificate: chained to `client_ca`, valid, for client
/// authentication, and not revoked by `crls` where they cover its issuer; with the number of CA
/// certificates. An error names its key (`client_ca` or `crl`).
fn client_verifier(
    settings: &config::Tls,
    crls: Vec<CertificateRevocationListDer<'static>>,
    provider: Arc<rustls::crypto::CryptoProvider>,
) -> Result<(Arc<dyn ClientCertVerifier>, usize), KeyedProblem> {
    let client_ca = settings.client_ca.display();
    let cas = pem::certificates(&settings.client_ca).map_err(|e| ("client_ca", e))?;
    let count = cas.len();
    let mut roots = RootCertStore::empty();
    let (_, unusable) = roots.add_parsable_certificates(cas);
    if unusable > 0 {
        return Err((
            "client_ca",
            format!("{client_ca}: {unusable} of its {count} certificates cannot be a CA"),
        ));
    }
    WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider)
        .with_crls(crls)
        // A CRL file need not cover every CA of the chain; those it covers are checked.
        .allow_unknown_revocation_status()
        .build()
        .map(|verifier| (verifier, count))
        .map_err(|e| match e {
            VerifierBuilderError::InvalidCrl(e) => {
                let crl = settings.crl.as_deref().unwrap_or(Path::new("")).display();
                ("crl", format!("{crl}: not a CRL that can be used: {e:?}"))
            }
            e => ("client_ca", format!("{client_ca}: {e}")),
        })
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
        let chain = pem::certificates(&settings.certificate)
            .and_then(|chain| Ok((inspect_chain(&settings.certificate, &chain)?, chain)))
            .map_err(|e| problems.fail("certificate", e))
            .ok();
        let key = pem::private_key(&settings.private_key)
            .map_err(|e| problems.fail("private_key", e))
            .ok();
        let crls = settings.crl.as_deref().map(pem::crls).transpose();
        // The CA file is checked even when the CRL file is broken: every problem in one report.
        let usable_crls = crls
            .as_ref()
            .map_or(Vec::new(), |crls| crls.clone().unwrap_or_default());
        let verifier = client_verifier(settings, usable_crls, provider.clone())
            .map_err(|(key, e)| problems.fail(key, e))
            .ok();
        let verifier = match crls {
            Ok(_) => verifier,
            Err(e) => {
                problems.fail("crl", e);
                None
            }
        };
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
    pub(crate) fn identify(&self, chain: Option<&[CertificateDer<'_>]>) -> Certified {
        let end_entity = chain.and_then(<[_]>::first).map(|der| parse(der));
        let (role, subject) = match &end_entity {
            Some(Ok(certificate)) => (role_of(certificate), certificate.subject().to_string()),
            _ => (Ok(None), String::new()),
        };
        let (role, role_problem) = match role {
            Ok(role) => (role, None),
            Err(problem) => (None, Some(problem)),
        };
        let listed = role
            .as_ref()
            .and_then(|name| self.roles.get_key_value(name));
        let (role_label, granted) = match listed {
            Some((name, granted)) => (name.clone(), *granted),
            None => (OTHER_ROLE.to_owned(), Role::from(self.default_access)),
        };
        Certified {
            role_label,
            role,
            role_problem,
            rights: rights(granted.access),
            units: granted.units,
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

/// The role in a certificate's RoleOID extension, `None` without one; an error when the
/// extension is there but not the UTF8String the spec says it is.
pub(crate) fn role_of(certificate: &X509Certificate<'_>) -> Result<Option<String>, &'static str> {
    let Some(extension) = certificate
        .extensions()
        .iter()
        .find(|extension| extension.oid.to_id_string() == ROLE_OID)
    else {
        return Ok(None);
    };
    match String::from_der(extension.value) {
        Ok(([], role)) => Ok(Some(role)),
        _ => Err("the RoleOID extension is not one ASN.1 UTF8String"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rcgen::{
        BasicConstraints, CertificateParams, CertifiedIssuer, CustomExtension, DnType,
        ExtendedKeyUsagePurpose, IsCa, KeyPair, KeyUsagePurpose, SanType,
    };
    use rustls::pki_types::pem::PemObject;
    use std::path::PathBuf;

    const ROLE: &[u64] = &[1, 3, 6, 1, 4, 1, 50316, 802, 1];

    /// A directory of PEM files for one test, removed at the end.
    struct Files(PathBuf);

    impl Files {
        fn new(name: &str) -> Files {
            let dir =
                std::env::temp_dir().join(format!("mbgw-tls-unit-{}-{name}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            Files(dir)
        }

        fn write(&self, name: &str, text: &str) -> PathBuf {
            let path = self.0.join(name);
            std::fs::write(&path, text).unwrap();
            path
        }
    }

    impl Drop for Files {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn ca(name: &str) -> CertifiedIssuer<'static, KeyPair> {
        let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
        params.distinguished_name.push(DnType::CommonName, name);
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        params.key_usages = vec![KeyUsagePurpose::KeyCertSign];
        CertifiedIssuer::self_signed(params, KeyPair::generate().unwrap()).unwrap()
    }

    /// A certificate signed by `ca`, its PEM and its key's PEM; `role` as the RoleOID's DER.
    fn issue(
        ca: &CertifiedIssuer<'static, KeyPair>,
        name: &str,
        role: Option<Vec<u8>>,
        days: i64,
    ) -> (String, String) {
        let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
        params.distinguished_name.push(DnType::CommonName, name);
        params.subject_alt_names = vec![SanType::IpAddress([127, 0, 0, 1].into())];
        let now = time::OffsetDateTime::now_utc();
        params.not_before = now - time::Duration::days(1);
        params.not_after = now + time::Duration::days(days);
        params.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        if let Some(der) = role {
            params
                .custom_extensions
                .push(CustomExtension::from_oid_content(ROLE, der));
        }
        let key = KeyPair::generate().unwrap();
        let cert = params.signed_by(&key, ca).unwrap();
        (cert.pem(), key.serialize_pem())
    }

    /// `text` as a DER UTF8String.
    fn utf8(text: &str) -> Vec<u8> {
        let mut der = vec![0x0C, u8::try_from(text.len()).unwrap()];
        der.extend_from_slice(text.as_bytes());
        der
    }

    fn settings(files: &Files, server: &(String, String), ca_pem: &str) -> config::Tls {
        config::Tls {
            certificate: files.write("server.crt", &server.0),
            private_key: files.write("server.key", &server.1),
            client_ca: files.write("ca.crt", ca_pem),
            crl: None,
            roles: [
                ("operator".to_owned(), RoleAccess::ReadWrite.into()),
                ("viewer".to_owned(), RoleAccess::ReadOnly.into()),
                (
                    "line2".to_owned(),
                    Role {
                        access: RoleAccess::ReadWrite,
                        units: Some("10-19".parse().unwrap()),
                    },
                ),
            ]
            .into(),
            default_role_access: RoleAccess::None,
            handshake_timeout: Duration::from_secs(10),
        }
    }

    fn keys(errors: ConfigErrors) -> Vec<String> {
        errors
            .0
            .into_iter()
            .map(|e| format!("{}: {}", e.key, e.reason))
            .collect()
    }

    #[test]
    fn the_role_is_the_role_oids_utf8_string_and_maps_through_the_table() {
        let files = Files::new("roles");
        let ca = ca("plant");
        let server = issue(&ca, "gateway", None, 90);
        let tls = TlsServer::load(&settings(&files, &server, &ca.pem())).unwrap();
        let identify = |role: Option<Vec<u8>>| {
            let (pem, _) = issue(&ca, "master", role, 90);
            let der = CertificateDer::from_pem_slice(pem.as_bytes()).unwrap();
            tls.identify(Some(&[der]))
        };
        let operator = identify(Some(utf8("operator")));
        assert_eq!(
            (
                operator.role_label.as_str(),
                operator.role.as_deref(),
                operator.rights
            ),
            ("operator", Some("operator"), Rights::ReadWrite)
        );
        assert_eq!(operator.subject, "CN=master");
        assert_eq!(identify(Some(utf8("viewer"))).rights, Rights::ReadOnly);
        assert_eq!(operator.units, None, "any unit");
        let line2 = identify(Some(utf8("line2")));
        assert_eq!(line2.rights, Rights::ReadWrite);
        assert_eq!(line2.units, Some("10-19".parse().unwrap()));
        // Unlisted, absent, in the wrong case, or not a UTF8String (a PrintableString): the
        // default, counted as `other`.
        for role in [
            Some(utf8("intern")),
            None,
            Some(utf8("Viewer")),
            Some(vec![0x13, 2, b'o', b'k']),
        ] {
            let other = identify(role.clone());
            let printable = role.as_ref().is_some_and(|der| der[0] == 0x13);
            assert_eq!(other.role_problem.is_some(), printable, "{role:?}");
            assert_eq!(
                (other.role_label.as_str(), other.rights),
                ("other", Rights::NoAccess),
                "{role:?}"
            );
        }
        assert_eq!(
            identify(Some(utf8("intern"))).role.as_deref(),
            Some("intern")
        );
    }

    #[test]
    fn a_key_that_is_not_the_certificates_is_refused_by_its_key() {
        let files = Files::new("mismatch");
        let ca = ca("plant");
        let (cert, _) = issue(&ca, "gateway", None, 90);
        let (_, other_key) = issue(&ca, "other", None, 90);
        let errors =
            keys(TlsServer::load(&settings(&files, &(cert, other_key), &ca.pem())).unwrap_err());
        assert_eq!(errors.len(), 1);
        assert!(
            errors[0].starts_with("server.tls.private_key: ")
                && errors[0].contains("is not the key of the certificate"),
            "{errors:?}"
        );
    }

    #[test]
    fn every_unreadable_or_empty_file_is_named_by_its_key_in_one_report() {
        let files = Files::new("broken");
        let mut settings = settings(&files, &(String::new(), String::new()), "not PEM\n");
        settings.certificate = files.0.join("missing.crt");
        settings.crl = Some(files.write("ca.crl", "-----BEGIN CERTIFICATE-----\n"));
        let errors = keys(TlsServer::load(&settings).unwrap_err());
        assert_eq!(errors.len(), 4, "{errors:?}");
        assert!(errors[3].starts_with("server.tls.crl: ") && errors[3].contains("ca.crl"));
        assert!(
            errors[0].starts_with("server.tls.certificate: cannot read ")
                && errors[0].contains("missing.crt")
        );
        assert!(
            errors[1].starts_with("server.tls.private_key: ")
                && errors[1].contains("no PEM private key")
        );
        assert!(
            errors[2].starts_with("server.tls.client_ca: ")
                && errors[2].contains("no PEM certificate")
        );
    }

    #[test]
    fn the_expiry_is_the_chains_earliest_and_warned_of_within_thirty_days() {
        let files = Files::new("expiry");
        let ca = ca("plant");
        // The server's own certificate lasts 90 days; the next one in its chain, 20.
        let (own, key) = issue(&ca, "gateway", None, 90);
        let (next, _) = issue(&ca, "intermediate", None, 20);
        let tls = TlsServer::load(&settings(&files, &(own + &next, key), &ca.pem())).unwrap();
        let now = SystemTime::now();
        let info = &tls.certificate;
        assert_eq!(info.days_left(now), Ok(19), "20 days less a few seconds");
        assert_eq!(info.client_cas, 1);
        let warning = info.expiry_warning(now).expect("a warning");
        assert!(warning.contains("expires in 19 days"), "{warning}");
        let later = now + Duration::from_secs(25 * 86_400);
        assert_eq!(info.days_left(later), Err(5));
        assert!(info
            .expiry_warning(later)
            .unwrap()
            .contains("expired 5 days ago"));
        assert_eq!(info.expiry(later), "5 days ago");
        let just_past = info.expires + Duration::from_secs(1);
        assert_eq!(
            info.days_left(just_past),
            Err(0),
            "expired is never \"0 days left\""
        );
        assert_eq!(
            info.expiry_warning(now - Duration::from_secs(20 * 86_400)),
            None
        );
    }
}
