//! Who may talk to the service: TLS (rustls through tonic, optionally verifying client
//! certificates) and bearer tokens, checked in one tower layer in front of every service except
//! `grpc.health.v1.Health`, so that load-balancer and kubelet probes keep working without a
//! secret.
//!
//! The same layer counts, in `posematch_requests_total`, the answers that no handler of ours
//! ever sees: UNAUTHENTICATED (refused here) and OUT_OF_RANGE (a request message over
//! `max_message_bytes`, refused by tonic's decoder before the handler runs).

use std::collections::HashSet;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::{Arc, RwLock};
use std::task::{Context, Poll};

use sha2::{Digest, Sha256};
use tonic::transport::{Certificate, Identity, ServerTlsConfig};

use crate::config::TlsFiles;
use crate::engine::Metrics;

/// Path prefix of the health service, which never needs a token.
const HEALTH_PREFIX: &str = "/grpc.health.v1.Health/";

/// A security file that cannot be used; the message names the setting and the file.
#[derive(Debug, thiserror::Error)]
pub enum SecurityFileError {
    #[error("{setting} = {}: {source}{}", path.display(), permission_hint(source))]
    Unreadable {
        setting: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{setting} = {}: not a PEM file (expected -----BEGIN ...)", path.display())]
    NotPem {
        setting: &'static str,
        path: PathBuf,
    },
    #[error("{setting} = {}: {message}", path.display())]
    Invalid {
        setting: &'static str,
        path: PathBuf,
        message: String,
    },
}

/// What to do about a file this process may not read: in a container the server runs as
/// another user than the one who owns a mounted key (the image's is 10001:10001).
fn permission_hint(error: &std::io::Error) -> String {
    if error.kind() != std::io::ErrorKind::PermissionDenied {
        return String::new();
    }
    // SAFETY: getuid and getgid cannot fail and touch no memory.
    let (uid, gid) = unsafe { (libc::getuid(), libc::getgid()) };
    format!(
        " (the server runs as uid {uid}, gid {gid}: make the file readable by them, e.g. chown {uid}:{gid} FILE && chmod 0400 FILE)"
    )
}

/// A PEM file's bytes; `setting` names it in errors.
pub(crate) fn read_pem(setting: &'static str, path: &Path) -> Result<Vec<u8>, SecurityFileError> {
    let bytes = std::fs::read(path).map_err(|source| SecurityFileError::Unreadable {
        setting,
        path: path.to_owned(),
        source,
    })?;
    if bytes.windows(11).any(|w| w == b"-----BEGIN ") {
        Ok(bytes)
    } else {
        Err(SecurityFileError::NotPem {
            setting,
            path: path.to_owned(),
        })
    }
}

/// The server's TLS configuration from its PEM files.
pub fn tls_config(files: &TlsFiles) -> Result<ServerTlsConfig, SecurityFileError> {
    let read = read_pem;
    let mut config = ServerTlsConfig::new().identity(Identity::from_pem(
        read("tls_cert", &files.cert)?,
        read("tls_key", &files.key)?,
    ));
    if let Some(client_ca) = &files.client_ca {
        config = config.client_ca_root(Certificate::from_pem(read("tls_client_ca", client_ca)?));
    }
    Ok(config)
}

/// The accepted bearer tokens, kept as SHA-256 digests (a lookup compares digests, never the
/// secret itself); reloaded from their file on demand (SIGHUP).
#[derive(Clone)]
pub struct AccessTokens {
    file: PathBuf,
    digests: Arc<RwLock<Arc<HashSet<[u8; 32]>>>>,
}

impl AccessTokens {
    /// Reads `file`: one token per line; blank lines and lines starting with `#` are ignored.
    pub fn load(file: &Path) -> Result<Self, SecurityFileError> {
        let tokens = Self {
            file: file.to_owned(),
            digests: Arc::default(),
        };
        tokens.reload()?;
        Ok(tokens)
    }

    /// Reads the file again; on an error the tokens in force stay. Returns how many tokens
    /// are now accepted.
    pub fn reload(&self) -> Result<usize, SecurityFileError> {
        let text = std::fs::read_to_string(&self.file).map_err(|source| {
            SecurityFileError::Unreadable {
                setting: "auth_tokens_file",
                path: self.file.clone(),
                source,
            }
        })?;
        let digests: HashSet<[u8; 32]> = text
            .lines()
            .map(str::trim)
            .filter(|line| !line.is_empty() && !line.starts_with('#'))
            .map(digest)
            .collect();
        let count = digests.len();
        if count == 0 {
            tracing::warn!(
                file = %self.file.display(),
                "the token file holds no token: every call except health is refused"
            );
        }
        *self.digests.write().expect("token lock") = Arc::new(digests);
        Ok(count)
    }

    /// Whether an `authorization` header value carries an accepted token.
    pub(crate) fn accepts(&self, authorization: Option<&http::HeaderValue>) -> bool {
        // The scheme's name is case-insensitive (RFC 9110), the token is not.
        let Some(token) = authorization.and_then(|v| v.to_str().ok()).and_then(|v| {
            v.get(..7)
                .filter(|scheme| scheme.eq_ignore_ascii_case("bearer "))
                .map(|_| &v[7..])
        }) else {
            return false;
        };
        self.digests
            .read()
            .expect("token lock")
            .contains(&digest(token.trim()))
    }
}

fn digest(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

/// The tower layer: checks tokens (when configured) and counts the statuses no handler sees.
#[derive(Clone)]
pub struct GateLayer {
    pub tokens: Option<AccessTokens>,
    pub metrics: Metrics,
}

impl<S> tower::Layer<S> for GateLayer {
    type Service = Gate<S>;

    fn layer(&self, inner: S) -> Gate<S> {
        Gate {
            inner,
            tokens: self.tokens.clone(),
            metrics: self.metrics.clone(),
        }
    }
}

#[derive(Clone)]
pub struct Gate<S> {
    inner: S,
    tokens: Option<AccessTokens>,
    metrics: Metrics,
}

type BoxFuture<T, E> = Pin<Box<dyn Future<Output = Result<T, E>> + Send>>;

impl<S, B> tower::Service<http::Request<B>> for Gate<S>
where
    S: tower::Service<http::Request<B>, Response = http::Response<tonic::body::Body>>
        + Clone
        + Send
        + 'static,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
    B: Send + 'static,
{
    type Response = http::Response<tonic::body::Body>;
    type Error = S::Error;
    type Future = BoxFuture<Self::Response, Self::Error>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<B>) -> Self::Future {
        let path = request.uri().path();
        let rpc = path.rsplit('/').next().unwrap_or("").to_owned();
        let needs_token = !path.starts_with(HEALTH_PREFIX);
        let refused = needs_token
            && self.tokens.as_ref().is_some_and(|tokens| {
                !tokens.accepts(request.headers().get(http::header::AUTHORIZATION))
            });
        if refused {
            self.count(&rpc, "UNAUTHENTICATED");
            tracing::info!(
                rpc = %rpc.escape_debug(),
                "refused a call without a valid bearer token"
            );
            let status = tonic::Status::unauthenticated(
                "a valid bearer token is required: send the metadata `authorization: Bearer <token>` with a token from the server's auth_tokens_file",
            );
            return Box::pin(std::future::ready(Ok(status.into_http())));
        }
        // The standard pattern: call the clone that was made ready.
        let clone = self.inner.clone();
        let mut inner = std::mem::replace(&mut self.inner, clone);
        let metrics = self.metrics.clone();
        Box::pin(async move {
            let response = inner.call(request).await?;
            // A trailers-only answer with OUT_OF_RANGE comes from the decoder, before any
            // handler (handlers never answer it): the request message was too large.
            let out_of_range = response
                .headers()
                .get("grpc-status")
                .is_some_and(|v| v.as_bytes() == b"11");
            if out_of_range {
                metrics
                    .requests
                    .with_label_values(&[rpc.as_str(), "OUT_OF_RANGE"])
                    .inc();
            }
            Ok(response)
        })
    }
}

impl<S> Gate<S> {
    fn count(&self, rpc: &str, code: &str) {
        self.metrics.requests.with_label_values(&[rpc, code]).inc();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Only a refused read gets the hint (tests run as root here, which no file mode stops,
    /// so the error is made by hand; deploy/test-containers.sh meets the real one).
    #[test]
    fn an_unreadable_file_says_which_user_must_read_it() {
        let refused = SecurityFileError::Unreadable {
            setting: "tls_key",
            path: "/run/secrets/key".into(),
            source: std::io::ErrorKind::PermissionDenied.into(),
        };
        let message = refused.to_string();
        let uid = unsafe { libc::getuid() };
        assert!(
            message.starts_with("tls_key = /run/secrets/key: "),
            "{message}"
        );
        assert!(message.contains(&format!("runs as uid {uid}")), "{message}");
        let missing = SecurityFileError::Unreadable {
            setting: "tls_key",
            path: "/run/secrets/key".into(),
            source: std::io::ErrorKind::NotFound.into(),
        };
        assert!(!missing.to_string().contains("uid"), "{missing}");
    }

    #[test]
    fn tokens_are_read_per_line_and_reloaded() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("tokens");
        std::fs::write(&file, "# line 4\nalpha\n\n  beta  \n").unwrap();
        let tokens = AccessTokens::load(&file).unwrap();
        let header = |v: &str| http::HeaderValue::from_str(v).unwrap();
        assert!(tokens.accepts(Some(&header("Bearer alpha"))));
        assert!(tokens.accepts(Some(&header("Bearer beta"))));
        assert!(tokens.accepts(Some(&header("bearer beta"))));
        assert!(!tokens.accepts(Some(&header("Bearer BETA"))));
        assert!(!tokens.accepts(Some(&header("Bearer # line 4"))));
        assert!(!tokens.accepts(Some(&header("alpha"))));
        assert!(!tokens.accepts(None));
        std::fs::write(&file, "gamma\n").unwrap();
        assert_eq!(tokens.reload().unwrap(), 1);
        assert!(!tokens.accepts(Some(&header("Bearer alpha"))));
        assert!(tokens.accepts(Some(&header("Bearer gamma"))));
        std::fs::remove_file(&file).unwrap();
        assert!(tokens.reload().is_err());
        assert!(
            tokens.accepts(Some(&header("Bearer gamma"))),
            "kept on error"
        );
    }

    #[test]
    fn tls_files_that_are_missing_or_not_pem_name_the_setting() {
        let dir = tempfile::tempdir().unwrap();
        let junk = dir.path().join("junk.pem");
        std::fs::write(&junk, "not a certificate").unwrap();
        let files = |cert: &Path, key: &Path| TlsFiles {
            cert: cert.to_owned(),
            key: key.to_owned(),
            client_ca: None,
        };
        let missing = tls_config(&files(&dir.path().join("nope.pem"), &junk))
            .unwrap_err()
            .to_string();
        assert!(missing.contains("tls_cert"), "{missing}");
        let not_pem = tls_config(&files(&junk, &junk)).unwrap_err().to_string();
        assert!(not_pem.contains("not a PEM"), "{not_pem}");
    }
}
