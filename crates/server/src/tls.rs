//! The daemon's TLS identity, checked before anything is served: each file must hold PEM of
//! the right kind, the key must be the certificate's, and the certificate must be valid now.
//! An expired or not-yet-valid certificate is refused rather than served with a warning: every
//! client would refuse it anyway, each with an error less clear than this one.

use rustls::crypto::ring::sign::any_supported_type;
use rustls::sign::CertifiedKey;
use rustls_pki_types::pem::PemObject;
use rustls_pki_types::{CertificateDer, PrivateKeyDer};
use std::path::Path;
use std::time::{SystemTime, UNIX_EPOCH};

/// The certificate chain and key at these paths as tonic takes them, once they have passed
/// every check; otherwise a message that names the file and what is wrong with it.
pub fn load(cert: &Path, key: &Path) -> Result<tonic::transport::Identity, String> {
    let read = |p: &Path, what: &str| {
        std::fs::read(p).map_err(|e| format!("cannot read the TLS {what} {}: {e}", p.display()))
    };
    let (cert_pem, key_pem) = (read(cert, "certificate")?, read(key, "key")?);
    check(&cert_pem, &key_pem, now_unix()).map_err(|e| match e {
        Problem::Cert(m) => format!("the TLS certificate {}: {m}", cert.display()),
        Problem::Key(m) => format!("the TLS key {}: {m}", key.display()),
    })?;
    Ok(tonic::transport::Identity::from_pem(cert_pem, key_pem))
}

/// The same identity as rustls takes it, for the HTTP server: HTTP/1.1 over TLS 1.2 or 1.3.
pub fn server_config(
    cert: &Path,
    key: &Path,
) -> Result<std::sync::Arc<rustls::ServerConfig>, String> {
    load(cert, key)?;
    let read = |p: &Path| std::fs::read(p).map_err(|e| format!("cannot read {}: {e}", p.display()));
    let (cert_pem, key_pem) = (read(cert)?, read(key)?);
    let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_slice_iter(&cert_pem)
        .collect::<Result<_, _>>()
        .map_err(|e| format!("the TLS certificate {}: {e:?}", cert.display()))?;
    let key = PrivateKeyDer::from_pem_slice(&key_pem)
        .map_err(|e| format!("the TLS key {}: {e:?}", key.display()))?;
    let mut c = rustls::ServerConfig::builder_with_provider(std::sync::Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .map_err(|e| format!("TLS: {e}"))?
    .with_no_client_auth()
    .with_single_cert(certs, key)
    .map_err(|e| format!("TLS: {e}"))?;
    c.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(std::sync::Arc::new(c))
}

fn now_unix() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs() as i64)
}

/// What is wrong, and with which file.
#[derive(Debug, PartialEq)]
enum Problem {
    Cert(String),
    Key(String),
}

fn check(cert_pem: &[u8], key_pem: &[u8], now: i64) -> Result<(), Problem> {
    let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_slice_iter(cert_pem)
        .collect::<Result<_, _>>()
        .map_err(|e| Problem::Cert(format!("is not PEM ({e:?})")))?;
    let Some(leaf) = certs.first() else {
        return Err(Problem::Cert(
            "holds no certificate (no \"BEGIN CERTIFICATE\" block)".into(),
        ));
    };
    let key = PrivateKeyDer::from_pem_slice(key_pem).map_err(|e| {
        Problem::Key(format!(
            "is not a PEM private key ({e:?}); PKCS#8, PKCS#1 and SEC1 keys are taken"
        ))
    })?;
    let signer = any_supported_type(&key)
        .map_err(|e| Problem::Key(format!("is not a key rustls can sign with: {e}")))?;
    CertifiedKey::new(certs.clone(), signer)
        .keys_match()
        .map_err(|_| {
            Problem::Key("does not match the certificate (it is the key of another one)".into())
        })?;
    let (_, parsed) = x509_parser::parse_x509_certificate(leaf)
        .map_err(|e| Problem::Cert(format!("does not parse as X.509: {e}")))?;
    let validity = parsed.validity();
    let (from, until) = (
        validity.not_before.timestamp(),
        validity.not_after.timestamp(),
    );
    if now < from {
        return Err(Problem::Cert(format!(
            "is not valid yet: from {} (is the clock right?)",
            validity.not_before
        )));
    }
    if now > until {
        return Err(Problem::Cert(format!(
            "expired on {}: renew it",
            validity.not_after
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn data(name: &str) -> Vec<u8> {
        std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../tests/data/tls")
                .join(name),
        )
        .unwrap()
    }

    #[test]
    fn a_certificate_and_key_are_checked_before_they_are_served() {
        let (cert, key, ca) = (data("server.pem"), data("server.key"), data("ca.pem"));
        // The test certificate is valid from 2026-12-01 for a hundred years.
        let now = 1_800_000_000;
        assert_eq!(check(&cert, &key, now), Ok(()));
        let why = |r: Result<(), Problem>| format!("{:?}", r.unwrap_err());
        // The key of another certificate (the CA's certificate with the server's key).
        let other = why(check(&ca, &key, now));
        assert!(
            other.contains("Key") && other.contains("does not match"),
            "{other}"
        );
        assert!(why(check(b"garbage", &key, now)).contains("no certificate"));
        assert!(why(check(&cert, b"garbage", now)).contains("not a PEM private key"));
        assert!(why(check(&key, &key, now)).contains("no certificate"));
        assert!(why(check(&cert, &key, 4_000_000_000_000)).contains("expired"));
        assert!(why(check(&cert, &key, 1_700_000_000)).contains("not valid yet"));
    }
}
