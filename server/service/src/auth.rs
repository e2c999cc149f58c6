//! Authentication: one tower layer in front of every gRPC service of the server, so that no
//! handler runs before the caller is known and a new RPC cannot be added without the check.
//!
//! A caller presents a bearer token in the request metadata (`authorization: Bearer <token>`, as
//! gRPC's own call credentials send it). The server keeps only SHA-256 digests of its tokens (the
//! tokens file); a token is random (256 bits, `radserve token`), so a plain digest is as good as a
//! password hash here, and it is looked up by digest, which reveals nothing about a wrong token's
//! closeness to a right one. The layer puts the caller's [`Principal`] into the request's
//! extensions; the handlers pass it to the core, which checks ownership and quotas.
//!
//! Health checking (`grpc.health.v1`) stays open: probes and load balancers carry no token.
//! Reflection is open only when configured so. With authentication off (a server on loopback),
//! every caller is [`Principal::local`].

use std::collections::HashMap;
use std::sync::Arc;
use std::task::{Context, Poll};

use futures_util::future::{Either, Ready};
use radserve_core::{Principal, Role};
use tonic::codegen::http;
use tonic::Status;

use crate::error::ServiceError;

/// Bytes of a SHA-256 digest.
pub type Digest = [u8; 32];

/// What the layer lets through, and as whom.
#[derive(Clone, Default)]
pub struct AuthPolicy {
    /// Principals by their tokens' digests; None: authentication is off.
    tokens: Option<Arc<HashMap<Digest, Principal>>>,
    /// Whether reflection answers callers without a token.
    open_reflection: bool,
}

impl std::fmt::Debug for AuthPolicy {
    fn fmt(&self, formatter: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never the digests: names and counts only.
        let principals = self.tokens.as_ref().map(|tokens| tokens.len());
        formatter.debug_struct("AuthPolicy").field("tokens", &principals).field("open_reflection", &self.open_reflection).finish()
    }
}

/// Methods a principal with the `monitor` role may call: they change nothing.
pub const MONITOR_METHODS: &[&str] = &["ServerInfo", "ListEnvs", "ListSessions", "DescribeSession"];
const SERVICE_PREFIX: &str = "/radserve.v1.RadServe/";
const HEALTH_PREFIX: &str = "/grpc.health.v1.Health/";
const REFLECTION_PREFIX: &str = "/grpc.reflection.";

impl AuthPolicy {
    /// No authentication: every caller is [`Principal::local`].
    pub fn off() -> AuthPolicy {
        AuthPolicy::default()
    }

    /// Callers must present one of these tokens (given by their digests).
    pub fn tokens(tokens: HashMap<Digest, Principal>, open_reflection: bool) -> AuthPolicy {
        AuthPolicy { tokens: Some(Arc::new(tokens)), open_reflection }
    }

    pub fn is_on(&self) -> bool {
        self.tokens.is_some()
    }

    /// Who calls `path` with these headers: Ok(None) for an open service (health), the principal
    /// otherwise, or the status that refuses the call.
    pub fn admit(&self, path: &str, headers: &http::HeaderMap) -> Result<Option<Principal>, ServiceError> {
        if path.starts_with(HEALTH_PREFIX) {
            return Ok(None);
        }
        let Some(tokens) = &self.tokens else { return Ok(Some(Principal::local())) };
        if path.starts_with(REFLECTION_PREFIX) && self.open_reflection {
            return Ok(None);
        }
        let token = bearer_token(headers)?;
        let principal = tokens.get(&digest(token.as_bytes())).ok_or_else(|| {
            ServiceError::Unauthenticated("the bearer token is not one this server accepts (revoked, mistyped, or for another server)".into())
        })?;
        if principal.role() == Role::Monitor {
            let method = path.strip_prefix(SERVICE_PREFIX);
            let allowed = method.is_some_and(|method| MONITOR_METHODS.contains(&method)) || path.starts_with(REFLECTION_PREFIX);
            if !allowed {
                return Err(ServiceError::PermissionDenied(format!(
                    "principal '{}' has the monitor role, which may call {} and nothing else; {path} needs the user role",
                    principal.name(),
                    MONITOR_METHODS.join(", ")
                )));
            }
        }
        Ok(Some(principal.clone()))
    }
}

/// The token of an `authorization: Bearer <token>` header.
fn bearer_token(headers: &http::HeaderMap) -> Result<&str, ServiceError> {
    let missing = || {
        ServiceError::Unauthenticated(
            "this server requires a bearer token: send metadata `authorization: Bearer <token>` (the Python client: \
             Client(..., token=...) or RADSERVE_TOKEN)"
                .into(),
        )
    };
    let value = headers.get(http::header::AUTHORIZATION).ok_or_else(missing)?;
    let value = value.to_str().map_err(|_| missing())?;
    match value.split_once(' ') {
        Some((scheme, token)) if scheme.eq_ignore_ascii_case("bearer") && !token.trim().is_empty() => Ok(token.trim()),
        _ => Err(ServiceError::Unauthenticated("the authorization metadata must be `Bearer <token>`".into())),
    }
}

/// SHA-256 of `bytes`.
pub fn digest(bytes: &[u8]) -> Digest {
    let digest = ring::digest::digest(&ring::digest::SHA256, bytes);
    digest.as_ref().try_into().expect("SHA-256 has 32 bytes")
}

/// A new token (`radserve_` and 64 hex digits: 256 random bits) and its digest in hex.
pub fn new_token() -> std::io::Result<(String, String)> {
    let mut bytes = [0u8; 32];
    bytes[..16].copy_from_slice(&radserve_shm::random_token()?);
    bytes[16..].copy_from_slice(&radserve_shm::random_token()?);
    let token = format!("radserve_{}", hex(&bytes));
    let hashed = hex(&digest(token.as_bytes()));
    Ok((token, hashed))
}

pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|byte| format!("{byte:02x}")).collect()
}

/// A digest from its 64 hex digits.
pub fn parse_digest(text: &str) -> Option<Digest> {
    let text = text.trim();
    if text.len() != 64 || !text.is_ascii() {
        return None;
    }
    let mut digest = [0u8; 32];
    for (index, byte) in digest.iter_mut().enumerate() {
        *byte = u8::from_str_radix(&text[2 * index..2 * index + 2], 16).ok()?;
    }
    Some(digest)
}

/// The layer: `Server::builder().layer(AuthLayer::new(policy))`.
#[derive(Clone, Debug)]
pub struct AuthLayer(Arc<AuthPolicy>);

impl AuthLayer {
    pub fn new(policy: AuthPolicy) -> AuthLayer {
        AuthLayer(Arc::new(policy))
    }
}

impl<S> tower::Layer<S> for AuthLayer {
    type Service = Authenticated<S>;

    fn layer(&self, inner: S) -> Authenticated<S> {
        Authenticated { inner, policy: self.0.clone() }
    }
}

/// A service behind the layer.
#[derive(Clone, Debug)]
pub struct Authenticated<S> {
    inner: S,
    policy: Arc<AuthPolicy>,
}

impl<S, B> tower::Service<http::Request<B>> for Authenticated<S>
where
    S: tower::Service<http::Request<B>, Response = http::Response<tonic::body::Body>>,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = Either<S::Future, Ready<Result<S::Response, S::Error>>>;

    fn poll_ready(&mut self, context: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(context)
    }

    fn call(&mut self, mut request: http::Request<B>) -> Self::Future {
        match self.policy.admit(request.uri().path(), request.headers()) {
            Ok(principal) => {
                if let Some(principal) = principal {
                    request.extensions_mut().insert(principal);
                }
                Either::Left(self.inner.call(request))
            }
            Err(error) => Either::Right(futures_util::future::ready(Ok(Status::from(error).into_http()))),
        }
    }
}

/// Who made the request: the authentication layer puts the principal in every request it lets
/// through, so a request without one never passed it.
pub(crate) fn caller<T>(request: &tonic::Request<T>) -> crate::error::Result<Principal> {
    request.extensions().get::<Principal>().cloned().ok_or_else(|| {
        ServiceError::Unauthenticated("this request did not pass the server's authentication layer".into())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use radserve_core::PrincipalLimits;

    fn headers(value: Option<&str>) -> http::HeaderMap {
        let mut headers = http::HeaderMap::new();
        if let Some(value) = value {
            headers.insert(http::header::AUTHORIZATION, value.parse().unwrap());
        }
        headers
    }

    fn code(result: Result<Option<Principal>, ServiceError>) -> tonic::Code {
        match result {
            Ok(_) => tonic::Code::Ok,
            Err(error) => Status::from(error).code(),
        }
    }

    #[test]
    fn tokens_map_to_principals_and_health_stays_open() {
        let (token, hashed) = new_token().unwrap();
        let (watcher, watcher_hash) = new_token().unwrap();
        assert!(token.starts_with("radserve_") && token.len() == 9 + 64);
        let mut tokens = HashMap::new();
        tokens.insert(parse_digest(&hashed).unwrap(), Principal::new("alice", Role::User, PrincipalLimits::default()));
        tokens.insert(parse_digest(&watcher_hash).unwrap(), Principal::new("grafana", Role::Monitor, PrincipalLimits::default()));
        let policy = AuthPolicy::tokens(tokens, false);
        let create = "/radserve.v1.RadServe/CreateSession";
        let alice = policy.admit(create, &headers(Some(&format!("Bearer {token}")))).unwrap().unwrap();
        assert_eq!(alice.name(), "alice");
        assert_eq!(policy.admit(create, &headers(Some(&format!("bearer  {token} ")))).unwrap().unwrap().name(), "alice");
        assert_eq!(code(policy.admit(create, &headers(None))), tonic::Code::Unauthenticated);
        assert_eq!(code(policy.admit(create, &headers(Some(&token)))), tonic::Code::Unauthenticated);
        assert_eq!(code(policy.admit(create, &headers(Some("Bearer radserve_00")))), tonic::Code::Unauthenticated);
        assert_eq!(code(policy.admit(create, &headers(Some(&format!("Bearer {watcher}"))))), tonic::Code::PermissionDenied);
        let list = "/radserve.v1.RadServe/ListSessions";
        assert_eq!(policy.admit(list, &headers(Some(&format!("Bearer {watcher}")))).unwrap().unwrap().name(), "grafana");
        assert!(policy.admit("/grpc.health.v1.Health/Check", &headers(None)).unwrap().is_none());
        let reflection = "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo";
        assert_eq!(code(policy.admit(reflection, &headers(None))), tonic::Code::Unauthenticated);
        assert_eq!(parse_digest("zz"), None);
        assert!(format!("{policy:?}").contains("Some(2)"), "Debug shows counts, never digests");
    }

    #[test]
    fn with_authentication_off_every_caller_is_local() {
        let policy = AuthPolicy::off();
        let caller = policy.admit("/radserve.v1.RadServe/Step", &headers(None)).unwrap().unwrap();
        assert_eq!(caller, Principal::local());
    }
}
