//! Reading the PEM files of TLS, on both sides of the gateway: the listeners' server certificate,
//! key, client CA and CRLs (`net::tls`), a Modbus TCP device's client certificate, key and CA
//! (`bus::device::tls`), and the MQTT broker's CA and the gateway's certificate (`mqtt`). Every
//! error names the file and says what it lacks. Knows nothing of what the files are for.

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, CertificateRevocationListDer, PrivateKeyDer};
use std::path::Path;

/// The bytes of `path`, or why it cannot be read.
pub(crate) fn read(path: &Path) -> Result<Vec<u8>, String> {
    std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))
}

/// The certificates of a PEM file, or why there are none.
pub(crate) fn certificates(path: &Path) -> Result<Vec<CertificateDer<'static>>, String> {
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

/// The certificates of a PEM file as the CAs a client trusts, or why they cannot be.
pub(crate) fn roots(path: &Path) -> Result<rustls::RootCertStore, String> {
    let mut roots = rustls::RootCertStore::empty();
    let (_, unusable) = roots.add_parsable_certificates(certificates(path)?);
    match (roots.is_empty(), unusable) {
        (false, 0) => Ok(roots),
        _ => Err(format!(
            "{}: {unusable} of its certificates cannot be a CA",
            path.display()
        )),
    }
}

/// The private key of a PEM file, or why there is none.
pub(crate) fn private_key(path: &Path) -> Result<PrivateKeyDer<'static>, String> {
    let pem = read(path)?;
    PrivateKeyDer::from_pem_slice(&pem).map_err(|e| {
        format!(
            "{}: holds no PEM private key (PKCS#8, PKCS#1 or SEC1): {e}",
            path.display()
        )
    })
}

/// The certificate revocation lists of a PEM file, or why there are none.
pub(crate) fn crls(path: &Path) -> Result<Vec<CertificateRevocationListDer<'static>>, String> {
    let pem = read(path)?;
    let crls = CertificateRevocationListDer::pem_slice_iter(&pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("{}: not a PEM file of CRLs: {e}", path.display()))?;
    if crls.is_empty() {
        return Err(format!(
            "{}: holds no PEM CRL (-----BEGIN X509 CRL-----)",
            path.display()
        ));
    }
    Ok(crls)
}
