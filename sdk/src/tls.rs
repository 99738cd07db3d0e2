//! TLS of the client: one rustls configuration (Mozilla's roots, plus any CA the user trusts)
//! for HTTPS (reqwest) and WSS (tokio-tungstenite), so a server behind an ingress, or a
//! relfusiond with its own TLS listener and a private CA, is reached the same way on both.

use std::sync::Arc;

use rustls::RootCertStore;
use rustls_pki_types::CertificateDer;
use rustls_pki_types::pem::PemObject as _;

use crate::error::ClientError;

/// The client's TLS configuration trusting the web's roots and every certificate of
/// `extra_ca_pem` (PEM, one or more; none when empty).
pub fn client_config(extra_ca_pem: &[u8]) -> Result<Arc<rustls::ClientConfig>, ClientError> {
    let bad = |why: String| ClientError::InvalidOption(format!("CA certificate: {why}"));
    let mut roots = RootCertStore::empty();
    roots.extend(webpki_roots::TLS_SERVER_ROOTS.iter().cloned());
    if !extra_ca_pem.is_empty() {
        let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_slice_iter(extra_ca_pem)
            .collect::<Result<_, _>>()
            .map_err(|e| bad(e.to_string()))?;
        if certs.is_empty() {
            return Err(bad("no PEM certificate in it".into()));
        }
        for cert in certs {
            roots.add(cert).map_err(|e| bad(e.to_string()))?;
        }
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| bad(e.to_string()))?
        .with_root_certificates(roots)
        .with_no_client_auth();
    Ok(Arc::new(config))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn garbage_is_not_a_ca() {
        assert!(client_config(b"").is_ok());
        let err = client_config(b"not a certificate").expect_err("refused");
        assert!(err.to_string().contains("CA certificate"), "{err}");
    }
}
