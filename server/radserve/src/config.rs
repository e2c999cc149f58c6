//! One configuration tree: defaults, then a TOML file, then `RADSERVE__SECTION__KEY` environment
//! variables (e.g. `RADSERVE__SIM__GL=osmesa`), validated at start-up.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;


use anyhow::{bail, Context};
use figment::providers::{Env, Format, Serialized, Toml};
use figment::Figment;
use std::collections::{HashMap, HashSet};

use radserve_core::{Limits, Principal, PrincipalLimits, Role};
use radserve_service::auth::{parse_digest, Digest};
use radserve_sim::GlBackend;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub server: ServerConfig,
    pub sim: SimConfig,
    pub augment: AugmentConfig,
    pub limits: Limits,
    pub replay: radserve_core::ReplayConfig,
    pub auth: AuthConfig,
    pub tls: TlsConfig,
    pub metrics: MetricsConfig,
    pub acting: ActingSection,
}

/// Server-side actors (SetPolicy, StartActing): where ONNX Runtime comes from and what a policy may
/// cost.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct ActingSection {
    /// The ONNX Runtime library (libonnxruntime.so). Unset: the one of the onnxruntime wheel
    /// installed in the workers' virtualenv (sim.venv), which the server's requirements include.
    pub onnxruntime_library: Option<PathBuf>,
    /// ONNX Runtime's intra-op threads per policy (in the policy's runtime process; 1: its main thread).
    pub threads: usize,
    /// The largest model SetPolicy takes, in bytes (the RAD actor is 12 MB).
    pub max_model_bytes: u64,
    /// The memory each policy may use, in bytes: the data memory (RLIMIT_DATA) of the process the
    /// policy runs in (ONNX Runtime's own ~20 MiB, the model's weights and every intermediate tensor;
    /// RAD's pixel actor at 8 envs peaks at ~75 MiB). Charged with the model's bytes to the session's owner (limits.memory_bytes and the
    /// principal's quota) while the session holds the policy; a model that needs more is refused at
    /// SetPolicy (RESOURCE_EXHAUSTED), or its actor fails.
    pub policy_memory_bytes: u64,
    /// Seconds a policy may take to be built and run once at SetPolicy.
    pub policy_load_timeout_s: f64,
    /// Seconds one inference may take before the actor fails.
    pub policy_call_timeout_s: f64,
}

impl Default for ActingSection {
    fn default() -> Self {
        ActingSection {
            onnxruntime_library: None,
            threads: 1,
            max_model_bytes: 64 << 20,
            policy_memory_bytes: radserve_core::DEFAULT_POLICY_MEMORY_BYTES,
            policy_load_timeout_s: 60.0,
            policy_call_timeout_s: 30.0,
        }
    }
}

impl ActingSection {
    pub fn to_core(&self) -> radserve_core::ActingConfig {
        radserve_core::ActingConfig {
            library: self.onnxruntime_library.clone(),
            python: None,
            program: None,
            threads: self.threads.max(1),
            max_model_bytes: usize::try_from(self.max_model_bytes).unwrap_or(usize::MAX),
            policy_memory_bytes: self.policy_memory_bytes,
            load_timeout: std::time::Duration::from_secs_f64(self.policy_load_timeout_s.clamp(0.1, 3600.0)),
            call_timeout: std::time::Duration::from_secs_f64(self.policy_call_timeout_s.clamp(0.1, 3600.0)),
        }
    }
}

/// The Prometheus endpoint (`GET /metrics`, OpenMetrics text; the README's "The server").
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct MetricsConfig {
    /// host:port of the HTTP endpoint, e.g. "127.0.0.1:9090" (or "0.0.0.0:9090" in a container for
    /// the cluster's Prometheus). Empty: off. It shows counts and sizes, no session ids or owners,
    /// and has no authentication: keep it on a port only the scraper reaches.
    pub address: String,
}

/// Who may call (docs/security.md).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct AuthConfig {
    /// A TOML file of principals and their tokens' SHA-256 digests (`radserve token` makes entries).
    /// Set: every call but health checks needs `authorization: Bearer <token>`. Unset: no
    /// authentication, which the server accepts only on a loopback address (or with mTLS, or with
    /// `server.insecure`).
    pub tokens_file: Option<PathBuf>,
    /// Let reflection (grpc.reflection v1 and v1alpha) answer callers without a token. The schema
    /// is public (the proto ships with the client); off by default all the same.
    pub open_reflection: bool,
}

/// TLS on the gRPC port (rustls). Both files set: TLS; `client_ca_file` too: clients must present a
/// certificate signed by that CA (mTLS).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct TlsConfig {
    /// PEM: the server's certificate chain.
    pub cert_file: Option<PathBuf>,
    /// PEM: its private key.
    pub key_file: Option<PathBuf>,
    /// PEM: the CA that signs client certificates.
    pub client_ca_file: Option<PathBuf>,
}

/// One principal of the tokens file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrincipalEntry {
    pub name: String,
    #[serde(default)]
    pub role: Role,
    /// Hex SHA-256 digests of the principal's tokens (several while rotating one).
    pub token_sha256: Vec<String>,
    /// Its limits on top of the server's (unset: only the server's apply).
    pub max_sessions: Option<usize>,
    pub max_envs: Option<usize>,
    pub memory_bytes: Option<u64>,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokensFile {
    #[serde(default)]
    pub principal: Vec<PrincipalEntry>,
}

impl TokensFile {
    pub fn load(path: &Path) -> anyhow::Result<TokensFile> {
        if !path.exists() {
            bail!("auth.tokens_file {} does not exist", path.display());
        }
        Figment::from(Toml::file(path))
            .extract()
            .with_context(|| format!("auth.tokens_file {} is not a valid tokens file (docs/security.md)", path.display()))
    }

    /// Principals by digest; every name and digest appears once, every digest is 64 hex digits.
    pub fn principals(&self) -> anyhow::Result<HashMap<Digest, Principal>> {
        let mut principals = HashMap::new();
        let mut names = HashSet::new();
        for entry in &self.principal {
            if entry.name.is_empty() || entry.name.len() > 64 || !entry.name.chars().all(|c| c.is_ascii_graphic()) {
                bail!("principal names are 1 to 64 printable ASCII characters without spaces, got {:?}", entry.name);
            }
            if !names.insert(entry.name.clone()) {
                bail!("principal '{}' appears twice in the tokens file; list all its tokens in one token_sha256", entry.name);
            }
            if entry.token_sha256.is_empty() {
                bail!("principal '{}' has no token_sha256", entry.name);
            }
            let limits =
                PrincipalLimits { max_sessions: entry.max_sessions, max_envs: entry.max_envs, memory_bytes: entry.memory_bytes };
            let principal = Principal::new(&entry.name, entry.role, limits);
            for text in &entry.token_sha256 {
                let digest = parse_digest(text).with_context(|| {
                    format!("principal '{}': token_sha256 entries are 64 hex digits (`radserve token` prints them)", entry.name)
                })?;
                if principals.insert(digest, principal.clone()).is_some() {
                    bail!("a token digest appears twice in the tokens file (principal '{}')", entry.name);
                }
            }
        }
        Ok(principals)
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct AugmentConfig {
    /// Threads that sample and augment minibatches; 0 means one per core.
    pub threads: usize,
    /// Niceness of the augmentation threads (0..=19): above 0, stepping (the gRPC handlers, the simulator
    /// workers) gets the cores first when both want them, and augmentation takes what is left.
    pub nice: i32,
    /// Run the augmentation threads in Linux's SCHED_IDLE class: they get a core only when no other
    /// thread of the host wants it, so stepping (the gRPC handlers, the simulator workers) never waits
    /// behind augmentation; augmentation gets what stepping leaves. Overrides nice.
    pub idle: bool,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    /// host:port of the gRPC port (port 0 picks a free one). On a non-loopback address the server
    /// starts only with authentication (auth.tokens_file or tls.client_ca_file) or server.insecure.
    pub address: String,
    /// Seconds from SIGTERM (or SIGINT) to exit, at most: streams end, calls finish, sessions close.
    /// A second signal exits at once.
    pub drain_timeout_s: f64,
    /// Seconds the server keeps answering after the signal (health NOT_SERVING, new sessions
    /// refused) before it closes its listener, so that probes and load balancers see it leave.
    pub shutdown_notice_s: f64,
    /// Connections open at once; more are closed as they arrive (lowered at start-up if the
    /// open-file limit cannot hold them).
    pub max_connections: usize,
    /// Seconds a connection may stay silent (no bytes from the peer) before it is closed. Live
    /// clients answer the keepalive pings, so only dead or non-gRPC peers reach it.
    pub idle_connection_timeout_s: f64,
    /// Seconds between the server's HTTP/2 pings on each connection (below the idle timeout).
    pub keepalive_interval_s: f64,
    /// Seconds a ping's answer may take before the connection is closed.
    pub keepalive_timeout_s: f64,
    /// Serve a non-loopback address with neither tokens nor client certificates: anyone who can
    /// reach the port can do anything. Off: such a start-up is refused.
    pub insecure: bool,
    /// Local users (uids) besides the server's own that may receive shared memory (shared
    /// stepping and batches); checked on the socket with SO_PEERCRED.
    pub shared_memory_uids: Vec<u32>,
    /// host:port of a second listener that serves grpc.health.v1 only, in plaintext and without
    /// tokens, for probes that cannot speak TLS or present a certificate (kubelet's gRPC probes)
    /// when the main port has TLS. It answers SERVING or NOT_SERVING as the main port does, and
    /// nothing else. Empty: none.
    pub health_address: String,
}

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            address: "127.0.0.1:50051".into(),
            drain_timeout_s: 20.0,
            shutdown_notice_s: 1.0,
            max_connections: 1024,
            idle_connection_timeout_s: 120.0,
            keepalive_interval_s: 30.0,
            keepalive_timeout_s: 20.0,
            insecure: false,
            shared_memory_uids: Vec::new(),
            health_address: String::new(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    /// Worker processes; 0 means one per core.
    pub workers: usize,
    /// OpenGL platform for MuJoCo rendering: "egl" (default) or "osmesa".
    #[schemars(with = "String")]
    pub gl: GlBackend,
    /// The virtualenv whose Python the workers embed. Unset: the virtualenv the executable is
    /// installed in (the wheel's layout), then $VIRTUAL_ENV, then a `.venv` found walking up from
    /// the executable (the layout `make setup` creates).
    pub venv: Option<PathBuf>,
    /// Seconds a worker may take to answer a reset, step or close before it is killed and replaced
    /// and the episodes it hosted end as truncated. Generous: a step of 64 default-look dm_control
    /// pixel envs renders for ~10 s on two cores.
    pub worker_call_timeout_s: f64,
    /// The same for building environments (creating a session's envs, the catalog at start-up).
    pub worker_create_timeout_s: f64,
    /// Seconds a worker may spend on one reset, step or close before health reports the RadServe
    /// and dm_env_rpc services NOT_SERVING (until it answers, or is killed at worker_call_timeout_s
    /// and replaced): readiness then sees a stuck worker before its deadline. The overall status ("")
    /// stays SERVING: the process lives.
    pub worker_stuck_after_s: f64,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            workers: 0,
            gl: GlBackend::default(),
            venv: None,
            worker_call_timeout_s: 60.0,
            worker_create_timeout_s: 300.0,
            worker_stuck_after_s: 20.0,
        }
    }
}

impl Config {
    pub fn load(file: Option<&Path>) -> anyhow::Result<Config> {
        let mut figment = Figment::from(Serialized::defaults(Config::default()));
        if let Some(file) = file {
            if !file.exists() {
                bail!("config file {} does not exist", file.display());
            }
            figment = figment.merge(Toml::file(file));
        }
        let config: Config = figment
            .merge(Env::prefixed("RADSERVE__").split("__"))
            .extract()
            .context("invalid configuration")?;
        config.validate()?;
        Ok(config)
    }

    pub fn validate(&self) -> anyhow::Result<()> {
        self.server
            .address
            .parse::<SocketAddr>()
            .with_context(|| format!("server.address '{}' is not a host:port socket address", self.server.address))?;
        if !self.server.health_address.is_empty() {
            self.server.health_address.parse::<SocketAddr>().with_context(|| {
                format!("server.health_address '{}' is not a host:port socket address (empty: none)", self.server.health_address)
            })?;
        }
        if !self.metrics.address.is_empty() {
            self.metrics.address.parse::<SocketAddr>().with_context(|| {
                format!("metrics.address '{}' is not a host:port socket address (empty: no metrics endpoint)", self.metrics.address)
            })?;
        }
        let server = &self.server;
        let seconds = |value: f64| value.is_finite() && (0.0..=86_400.0).contains(&value);
        let positive = |value: f64| seconds(value) && value > 0.0;
        if !positive(server.idle_connection_timeout_s) || !positive(server.keepalive_interval_s) || !positive(server.keepalive_timeout_s) {
            bail!(
                "server.idle_connection_timeout_s, keepalive_interval_s and keepalive_timeout_s are seconds in (0, 86400], got {}, {} and {}",
                server.idle_connection_timeout_s,
                server.keepalive_interval_s,
                server.keepalive_timeout_s
            );
        }
        if server.keepalive_interval_s >= server.idle_connection_timeout_s {
            bail!(
                "server.keepalive_interval_s ({}) must be below server.idle_connection_timeout_s ({}): the pings are what keeps a live but quiet client from being idle",
                server.keepalive_interval_s,
                server.idle_connection_timeout_s
            );
        }
        if server.max_connections == 0 {
            bail!("server.max_connections must be at least 1");
        }
        if !seconds(server.drain_timeout_s) || !seconds(server.shutdown_notice_s) {
            bail!(
                "server.drain_timeout_s and server.shutdown_notice_s are seconds in [0, 86400], got {} and {}",
                server.drain_timeout_s,
                server.shutdown_notice_s
            );
        }
        let positive = |value: f64| value.is_finite() && value > 0.0 && value <= 86_400.0;
        if !positive(self.sim.worker_call_timeout_s)
            || !positive(self.sim.worker_create_timeout_s)
            || !positive(self.sim.worker_stuck_after_s)
        {
            bail!(
                "sim.worker_call_timeout_s, sim.worker_create_timeout_s and sim.worker_stuck_after_s are seconds in \
                 (0, 86400], got {}, {} and {}",
                self.sim.worker_call_timeout_s,
                self.sim.worker_create_timeout_s,
                self.sim.worker_stuck_after_s
            );
        }
        let replay = &self.replay;
        if !positive(replay.snapshot_interval_s) {
            bail!("replay.snapshot_interval_s is seconds in (0, 86400], got {}", replay.snapshot_interval_s);
        }
        if let Some(dir) = &replay.snapshot_dir {
            if dir.as_os_str().is_empty() || dir.is_file() {
                bail!("replay.snapshot_dir {} is not a directory (it is made if it does not exist)", dir.display());
            }
        }
        let limits = &self.limits;
        if !(0..=19).contains(&self.augment.nice) {
            bail!("augment.nice must be between 0 and 19 (a lower priority than the server's), got {}", self.augment.nice);
        }
        if limits.max_sessions == 0
            || limits.max_envs_per_session == 0
            || limits.max_total_envs == 0
            || limits.max_streams_per_session == 0
            || limits.stream_memory_bytes == 0
        {
            bail!("limits must all be at least 1, got {limits:?}");
        }
        Ok(())
    }

    /// The authentication policy and TLS files, read and checked; refuses an open server on a
    /// reachable address.
    pub fn security(&self) -> anyhow::Result<crate::Security> {
        let tls = &self.tls;
        let read = |path: &PathBuf, what: &str| {
            std::fs::read(path).with_context(|| format!("reading {what} {}", path.display()))
        };
        let tls_files = match (&tls.cert_file, &tls.key_file) {
            (Some(cert), Some(key)) => Some(crate::TlsFiles {
                cert_pem: read(cert, "tls.cert_file")?,
                key_pem: read(key, "tls.key_file")?,
                client_ca_pem: tls.client_ca_file.as_ref().map(|ca| read(ca, "tls.client_ca_file")).transpose()?,
            }),
            (None, None) if tls.client_ca_file.is_some() => {
                bail!("tls.client_ca_file needs tls.cert_file and tls.key_file: client certificates are checked in a TLS handshake")
            }
            (None, None) => None,
            _ => bail!("tls.cert_file and tls.key_file are set together"),
        };
        let auth = match &self.auth.tokens_file {
            Some(path) => {
                let principals = TokensFile::load(path)?.principals()?;
                if principals.is_empty() {
                    bail!("auth.tokens_file {} lists no principal: nobody could call this server", path.display());
                }
                radserve_service::auth::AuthPolicy::tokens(principals, self.auth.open_reflection)
            }
            None => radserve_service::auth::AuthPolicy::off(),
        };
        let address: SocketAddr = self.server.address.parse().context("server.address")?;
        let mtls = tls_files.as_ref().is_some_and(|files| files.client_ca_pem.is_some());
        if !address.ip().is_loopback() && !auth.is_on() && !mtls && !self.server.insecure {
            bail!(
                "refusing to serve {address} without authentication: anyone who can reach it could use and close every \
                 session. Set auth.tokens_file (and TLS), or tls.client_ca_file (mTLS), or bind 127.0.0.1; \
                 `--insecure` (server.insecure) serves it open all the same (docs/security.md)"
            );
        }
        Ok(crate::Security { auth, tls: tls_files, loopback: address.ip().is_loopback() })
    }

    pub fn serve_options(&self) -> crate::ServeOptions {
        crate::ServeOptions {
            augment_threads: self.augment.threads,
            augment_nice: self.augment.nice,
            augment_idle: self.augment.idle,
            drain_timeout: Duration::from_secs_f64(self.server.drain_timeout_s),
            shutdown_notice: Duration::from_secs_f64(self.server.shutdown_notice_s),
            max_connections: self.server.max_connections,
            idle_connection_timeout: Duration::from_secs_f64(self.server.idle_connection_timeout_s),
            keepalive_interval: Duration::from_secs_f64(self.server.keepalive_interval_s),
            keepalive_timeout: Duration::from_secs_f64(self.server.keepalive_timeout_s),
            security: crate::Security::default(),
            shared_memory_uids: self.server.shared_memory_uids.clone(),
            health_address: (!self.server.health_address.is_empty()).then(|| self.server.health_address.clone()),
            worker_stuck_after: Duration::from_secs_f64(self.sim.worker_stuck_after_s),
        }
    }

    pub fn worker_count(&self) -> usize {
        if self.sim.workers > 0 {
            self.sim.workers
        } else {
            std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
        }
    }

    pub fn resolve_venv(&self) -> anyhow::Result<PathBuf> {
        if let Some(venv) = &self.sim.venv {
            return Ok(venv.clone());
        }
        let exe = std::env::current_exe().context("locating the radserve executable")?;
        // Installed from the wheel: the executable sits in a virtualenv's bin/, beside its python,
        // and that environment holds the simulators it was installed with, whichever one is active.
        if let Some(prefix) = exe.parent().and_then(Path::parent) {
            if prefix.join("pyvenv.cfg").exists() && prefix.join("bin/python").exists() {
                return Ok(prefix.to_path_buf());
            }
        }
        if let Some(active) = std::env::var_os("VIRTUAL_ENV") {
            return Ok(PathBuf::from(active));
        }
        for dir in exe.ancestors().skip(1) {
            let candidate = dir.join(".venv");
            if candidate.join("bin/python").exists() {
                return Ok(candidate);
            }
        }
        bail!(
            "no Python virtualenv found for the simulators: install radserve-server into one (`pip install radserve-server` \
             in a venv), activate one that has it, run `make setup` in a clone, or set sim.venv (RADSERVE__SIM__VENV)"
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid() {
        Config::default().validate().unwrap();
    }

    #[test]
    fn a_bad_address_is_rejected_at_start_up() {
        let mut config = Config::default();
        config.server.address = "localhost".into();
        assert!(config.validate().unwrap_err().to_string().contains("server.address"));
    }

    #[test]
    #[allow(clippy::result_large_err)] // figment::Jail's closure signature, not ours
    fn files_and_environment_override_defaults() {
        figment::Jail::expect_with(|jail| {
            jail.create_file("radserve.toml", "[sim]\nworkers = 3\n[limits]\nmax_sessions = 5\n")?;
            jail.set_env("RADSERVE__SIM__GL", "osmesa");
            let config = Config::load(Some(Path::new("radserve.toml"))).expect("loads");
            assert_eq!(config.sim.workers, 3);
            assert_eq!(config.sim.gl, GlBackend::Osmesa);
            assert_eq!(config.limits.max_sessions, 5);
            assert_eq!(config.limits.max_total_envs, Limits::default().max_total_envs);
            Ok(())
        });
    }
}
