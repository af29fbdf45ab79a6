//! TLS on the HTTP port, from the same PEM files as gRPC's (`tls_cert`, `tls_key`,
//! `tls_client_ca`), so a server that speaks TLS speaks it on every port.
//!
//! Handshakes run in their own tasks: a client that opens a connection and never completes its
//! handshake holds only its own task (for at most [`HANDSHAKE_TIMEOUT`]), never the accept loop.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_rustls::TlsAcceptor;
use tokio_rustls::server::TlsStream;

use crate::config::TlsFiles;
use crate::grpc::security::SecurityFileError;

/// How long a client has to complete its TLS handshake.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// Connections whose handshake is done, waiting for the HTTP server to take them.
const READY_CONNECTIONS: usize = 64;

/// The acceptor for the HTTP port: the server's certificate chain and key, client certificates
/// required and verified against `client_ca` when it is set (mutual TLS).
pub fn acceptor(files: &TlsFiles) -> Result<TlsAcceptor, SecurityFileError> {
    let invalid = |setting: &'static str, path: &std::path::Path, message: String| {
        SecurityFileError::Invalid {
            setting,
            path: path.to_owned(),
            message,
        }
    };
    let certificates = |setting: &'static str, path: &std::path::Path| {
        let pem = crate::grpc::security::read_pem(setting, path)?;
        let chain = CertificateDer::pem_slice_iter(&pem)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| invalid(setting, path, e.to_string()))?;
        if chain.is_empty() {
            return Err(invalid(setting, path, "no CERTIFICATE block".into()));
        }
        Ok(chain)
    };
    let chain = certificates("tls_cert", &files.cert)?;
    let key =
        PrivateKeyDer::from_pem_slice(&crate::grpc::security::read_pem("tls_key", &files.key)?)
            .map_err(|e| invalid("tls_key", &files.key, e.to_string()))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
        .with_safe_default_protocol_versions()
        .map_err(|e| invalid("tls_cert", &files.cert, e.to_string()))?;
    let builder = match &files.client_ca {
        Some(path) => {
            let mut roots = rustls::RootCertStore::empty();
            for certificate in certificates("tls_client_ca", path)? {
                roots
                    .add(certificate)
                    .map_err(|e| invalid("tls_client_ca", path, e.to_string()))?;
            }
            let verifier =
                rustls::server::WebPkiClientVerifier::builder_with_provider(roots.into(), provider)
                    .build()
                    .map_err(|e| invalid("tls_client_ca", path, e.to_string()))?;
            builder.with_client_cert_verifier(verifier)
        }
        None => builder.with_no_client_auth(),
    };
    let mut config = builder
        .with_single_cert(chain, key)
        .map_err(|e| invalid("tls_key", &files.key, e.to_string()))?;
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(TlsAcceptor::from(Arc::new(config)))
}

/// A listener that hands the HTTP server connections whose TLS handshake is done.
pub struct TlsListener {
    ready: mpsc::Receiver<(TlsStream<TcpStream>, SocketAddr)>,
    local_addr: std::io::Result<SocketAddr>,
}

impl TlsListener {
    /// Starts accepting on `listener`; the accept loop ends when this listener is dropped.
    pub fn new(listener: TcpListener, acceptor: TlsAcceptor) -> Self {
        let local_addr = listener.local_addr();
        let (sender, ready) = mpsc::channel(READY_CONNECTIONS);
        tokio::spawn(async move {
            loop {
                let accepted = tokio::select! {
                    accepted = listener.accept() => accepted,
                    _ = sender.closed() => return,
                };
                let (tcp, peer) = match accepted {
                    Ok(accepted) => accepted,
                    Err(e) => {
                        // Out of file descriptors and the like: wait instead of spinning.
                        tracing::warn!(error = %e, "the HTTP port could not accept a connection");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                        continue;
                    }
                };
                let (acceptor, sender) = (acceptor.clone(), sender.clone());
                tokio::spawn(async move {
                    match tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(tcp)).await {
                        Ok(Ok(stream)) => {
                            let _ = sender.send((stream, peer)).await;
                        }
                        Ok(Err(e)) => tracing::debug!(%peer, error = %e, "TLS handshake failed"),
                        Err(_) => tracing::debug!(%peer, "TLS handshake timed out"),
                    }
                });
            }
        });
        Self { ready, local_addr }
    }
}

impl axum::serve::Listener for TlsListener {
    type Io = TlsStream<TcpStream>;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        match self.ready.recv().await {
            Some(connection) => connection,
            // The accept loop ended: no connection will come again.
            None => std::future::pending().await,
        }
    }

    fn local_addr(&self) -> std::io::Result<Self::Addr> {
        match &self.local_addr {
            Ok(addr) => Ok(*addr),
            Err(e) => Err(std::io::Error::new(e.kind(), e.to_string())),
        }
    }
}
