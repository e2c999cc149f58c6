//! The radserve server, assembled: the simulator core behind the gRPC service, with health checking,
//! reflection and graceful shutdown. `main.rs` is the command line around it.

pub mod augment_cli;
pub mod config;
pub mod config_reference;
mod health;
pub mod metrics;
pub mod incoming;

use std::future::Future;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use radserve_service::{
    proto::FILE_DESCRIPTOR_SET, EnvironmentServer, EnvironmentService, RadServeServer, RadServeService, MAX_MESSAGE_BYTES,
};
use radserve_core::{Limits, SessionManager};
use radserve_sim::{GlBackend, WorkerLauncher, WorkerPool};
use tokio::net::TcpListener;
use tracing::{info, warn};

/// Everything the server needs to start its workers.
pub struct ServerSettings {
    /// The executable started in `worker` mode (normally this very binary).
    pub worker_program: PathBuf,
    pub venv: PathBuf,
    pub gl: GlBackend,
    pub workers: usize,
    pub limits: Limits,
    /// Snapshots of named sessions' replay (the `[replay]` section).
    pub replay: radserve_core::ReplayConfig,
    /// A worker that does not answer a reset, step or close within this is killed and replaced.
    pub worker_call_timeout: Duration,
    /// The same for building environments.
    pub worker_create_timeout: Duration,
    /// Server-side policies (the `[acting]` section); ONNX Runtime is looked for beside the
    /// workers' Python unless a library is named.
    pub acting: radserve_core::ActingConfig,
}

/// The worker pool and the sessions hosted in it. The pool is returned too, for an exit that
/// cannot wait (`WorkerPool::kill_all`).
pub fn session_manager(settings: ServerSettings) -> (Arc<SessionManager>, Arc<WorkerPool>) {
    let launcher = WorkerLauncher {
        call_timeout: settings.worker_call_timeout,
        create_timeout: settings.worker_create_timeout,
        ..WorkerLauncher::new(settings.worker_program, settings.venv.clone(), settings.gl)
    };
    let mut acting = settings.acting;
    acting.python.get_or_insert_with(|| settings.venv.join("bin/python"));
    let pool = Arc::new(WorkerPool::start(launcher, settings.workers));
    (Arc::new(SessionManager::new(pool.clone(), settings.limits).with_snapshots(settings.replay).with_acting(acting)), pool)
}

/// How the server serves and stops (the `[server]` and `[augment]` sections of the configuration).
#[derive(Clone, Debug)]
pub struct ServeOptions {
    /// Threads that sample and augment minibatches; 0: one per core.
    pub augment_threads: usize,
    /// Niceness of the augmentation threads (0: the server's own priority).
    pub augment_nice: i32,
    /// The augmentation threads in the SCHED_IDLE class (`augment.idle`).
    pub augment_idle: bool,
    /// From the shutdown signal to exit, at most.
    pub drain_timeout: Duration,
    /// How long the server keeps answering (NOT_SERVING, new sessions refused) before it stops
    /// accepting connections, so that health probes and load balancers see it leave.
    pub shutdown_notice: Duration,
    /// Connections open at once (more are closed as they arrive).
    pub max_connections: usize,
    /// A connection whose peer sends nothing for this long is closed.
    pub idle_connection_timeout: Duration,
    /// The server pings every connection this often (HTTP/2 PING) and closes one that does not
    /// answer within `keepalive_timeout`.
    pub keepalive_interval: Duration,
    pub keepalive_timeout: Duration,
    /// Authentication and TLS.
    pub security: Security,
    /// Users besides the server's own that may receive shared memory (acting, batches).
    pub shared_memory_uids: Vec<u32>,
    /// A plaintext listener serving grpc.health.v1 only (`server.health_address`).
    pub health_address: Option<String>,
    /// A worker in one reset, step or close for longer than this turns the RadServe and dm_env_rpc
    /// services NOT_SERVING until it answers or is replaced (`sim.worker_stuck_after_s`).
    pub worker_stuck_after: Duration,
}

/// Who may call, and over what (`[auth]`, `[tls]`; docs/security.md).
#[derive(Clone, Debug)]
pub struct Security {
    pub auth: radserve_service::auth::AuthPolicy,
    pub tls: Option<TlsFiles>,
    /// Whether the server listens on a loopback address only.
    pub loopback: bool,
}

impl Default for Security {
    fn default() -> Self {
        Security { auth: radserve_service::auth::AuthPolicy::off(), tls: None, loopback: true }
    }
}

/// PEM contents of the TLS files.
#[derive(Clone)]
pub struct TlsFiles {
    pub cert_pem: Vec<u8>,
    pub key_pem: Vec<u8>,
    /// Set: clients must present a certificate this CA signed (mTLS).
    pub client_ca_pem: Option<Vec<u8>>,
}

impl std::fmt::Debug for TlsFiles {
    fn fmt(&self, formatter: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        formatter.debug_struct("TlsFiles").field("mtls", &self.client_ca_pem.is_some()).finish_non_exhaustive()
    }
}

impl TlsFiles {
    fn server_config(&self) -> tonic::transport::ServerTlsConfig {
        let identity = tonic::transport::Identity::from_pem(&self.cert_pem, &self.key_pem);
        let config = tonic::transport::ServerTlsConfig::new().identity(identity);
        match &self.client_ca_pem {
            Some(ca) => config.client_ca_root(tonic::transport::Certificate::from_pem(ca)),
            None => config,
        }
    }
}

impl Default for ServeOptions {
    fn default() -> Self {
        ServeOptions {
            augment_threads: 0,
            augment_nice: 0,
            augment_idle: false,
            drain_timeout: Duration::from_secs(20),
            shutdown_notice: Duration::from_secs(1),
            max_connections: 1024,
            idle_connection_timeout: Duration::from_secs(120),
            keepalive_interval: Duration::from_secs(30),
            keepalive_timeout: Duration::from_secs(20),
            security: Security::default(),
            shared_memory_uids: Vec::new(),
            health_address: None,
            worker_stuck_after: Duration::from_secs(20),
        }
    }
}

/// Lowers the calling thread's priority: into SCHED_IDLE with `idle`, else by `nice` (Linux:
/// scheduling class and niceness are per thread).
fn lower_thread_priority(nice: i32, idle: bool) {
    if idle {
        let param = libc::sched_param { sched_priority: 0 };
        // SAFETY: sched_setscheduler reads the struct passed by pointer; pid 0 is the calling thread.
        if unsafe { libc::sched_setscheduler(0, libc::SCHED_IDLE, &param) } != 0 {
            warn!(error = %std::io::Error::last_os_error(), "could not put an augmentation thread in SCHED_IDLE");
        }
        return;
    }
    if nice <= 0 {
        return;
    }
    // SAFETY: gettid and setpriority only read and return integers; the id is this thread's own.
    let failed = unsafe { libc::setpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t, nice) } != 0;
    if failed {
        warn!(nice, error = %std::io::Error::last_os_error(), "could not lower an augmentation thread's priority");
    }
}

/// The health-only listener (`server.health_address`): grpc.health.v1 and nothing else, in plaintext
/// and without the auth layer, answering from the same reporter as the main port (so NOT_SERVING while
/// the catalog builds, a worker is stuck, or the server drains). Kept to a few connections: probes
/// need one at a time. Runs until the returned task is aborted, after the main port has stopped.
async fn serve_health_only(
    address: &str,
    reporter: tonic_health::server::HealthReporter,
    options: &ServeOptions,
) -> anyhow::Result<tokio::task::JoinHandle<()>> {
    use anyhow::Context;
    let health = tonic_health::pb::health_server::HealthServer::new(tonic_health::server::HealthService::from_health_reporter(reporter));
    let listener = TcpListener::bind(address).await.with_context(|| format!("binding server.health_address {address}"))?;
    info!(address = %listener.local_addr()?, "grpc.health.v1 only, plaintext (server.health_address)");
    let connections =
        incoming::incoming(listener, incoming::ConnectionLimits { max_connections: 16, idle_timeout: options.idle_connection_timeout });
    let server = tonic::transport::Server::builder().add_service(health).serve_with_incoming(connections);
    Ok(tokio::spawn(async move {
        if let Err(error) = server.await {
            warn!(%error, "the health-only listener stopped");
        }
    }))
}

/// Serves on `listener` until `shutdown` resolves, then drains within `options.drain_timeout`:
/// health turns NOT_SERVING at once and new sessions are refused (UNAVAILABLE); open streams end with
/// an UNAVAILABLE status; after `shutdown_notice` the listener closes and calls in flight finish;
/// then every session is closed and its workers' envs released. Whatever is still running at the
/// deadline is dropped.
pub async fn serve(
    listener: TcpListener,
    manager: Arc<SessionManager>,
    options: ServeOptions,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    // Every connection costs a file descriptor: sized from what the open-file limit leaves once the
    // server's own descriptors (workers' pipes and memory, the listeners) are open.
    let max_connections = incoming::connection_capacity(options.max_connections)?;
    // Minibatch augmentation runs here, never on tokio's workers; 0 threads: one per core.
    let augment_pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(options.augment_threads)
            .thread_name(|index| format!("radserve-augment-{index}"))
            .start_handler(move |_| lower_thread_priority(options.augment_nice, options.augment_idle))
            .build()?,
    );
    let (health_reporter, health_service) = tonic_health::server::health_reporter();
    // NOT_SERVING until the catalog is built (below), while a worker is stuck, and from shutdown on.
    let health = health::Health::new(health_reporter.clone()).await;
    let health_only = match &options.health_address {
        Some(address) => Some(serve_health_only(address, health_reporter.clone(), &options).await?),
        None => None,
    };
    // Both reflection versions: grpcurl and grpcui speak v1, grpc_cli, grpcio-reflection's Python
    // client and Postman still v1alpha.
    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let (reflection_v1, reflection_v1alpha) = (reflection().build_v1()?, reflection().build_v1alpha()?);
    let peers = radserve_service::handoff::PeerPolicy::new(&options.shared_memory_uids);
    let (service, streams) = RadServeService::new(manager.clone(), augment_pool, peers);
    // DeepMind's dm_env_rpc on the same port, over the same sessions (docs/dm_env_rpc.md).
    let environment = EnvironmentServer::new(EnvironmentService::new(manager.clone(), service.stopping()))
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let service = RadServeServer::new(service)
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);

    // Learn the env names in the background (a first CreateSession waits for them), and the catalog
    // after them; SERVING once it is built.
    let catalog = tokio::spawn(health.clone().build_catalog(manager.clone()));

    // Sessions whose lease expired (a learner that died without closing them) are closed here.
    let reaper = tokio::spawn(manager.clone().run_reaper());
    // Named sessions' replay, written to `[replay] snapshot_dir` every snapshot_interval_s.
    let snapshots = tokio::spawn(manager.clone().run_snapshots());

    let (stop_accepting, accepting_stopped) = tokio::sync::oneshot::channel::<()>();
    let (signalled, signal_seen) = tokio::sync::oneshot::channel::<tokio::time::Instant>();
    let stuck_watch = tokio::spawn(health.clone().watch_stuck_workers(manager.clone(), options.worker_stuck_after));
    let draining = manager.clone();
    let notice = options.shutdown_notice.min(options.drain_timeout);
    tokio::spawn(async move {
        shutdown.await;
        // Ended first; the draining state keeps every status NOT_SERVING whatever they would publish.
        stuck_watch.abort();
        catalog.abort();
        let started = tokio::time::Instant::now();
        let _ = signalled.send(started);
        info!(notice_s = notice.as_secs_f64(), "shutting down: not serving, new sessions refused, streams ending");
        health.drain().await;
        draining.refuse_new_sessions();
        streams.stop();
        tokio::time::sleep_until(started + notice).await;
        let _ = stop_accepting.send(());
    });
    let graceful = async move {
        let _ = accepting_stopped.await;
        info!("shutting down: listener closed, finishing the calls in flight");
    };
    if max_connections < options.max_connections {
        warn!(configured = options.max_connections, max_connections, "server.max_connections lowered to fit the open-file limit");
    }
    let connections = incoming::incoming(
        listener,
        incoming::ConnectionLimits { max_connections, idle_timeout: options.idle_connection_timeout },
    );
    let security = &options.security;
    if security.auth.is_on() && security.tls.is_none() && !security.loopback {
        warn!("bearer tokens travel in clear text: this server is reachable beyond loopback without TLS (set tls.cert_file and tls.key_file)");
    }
    info!(
        authentication = if security.auth.is_on() { "tokens" } else { "off" },
        tls = match &security.tls {
            None => "off",
            Some(TlsFiles { client_ca_pem: None, .. }) => "on",
            Some(TlsFiles { client_ca_pem: Some(_), .. }) => "mutual",
        },
        "security"
    );
    let mut builder = tonic::transport::Server::builder()
        .http2_keepalive_interval(Some(options.keepalive_interval))
        .http2_keepalive_timeout(Some(options.keepalive_timeout));
    if let Some(tls) = &security.tls {
        builder = builder.tls_config(tls.server_config())?;
    }
    let server = builder
        .layer(radserve_service::auth::AuthLayer::new(security.auth.clone()))
        .add_service(health_service)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(service)
        .add_service(environment)
        .serve_with_incoming_shutdown(connections, graceful);
    tokio::pin!(server);
    let mut signal_seen = signal_seen;
    let deadline = tokio::select! {
        result = &mut server => {
            result?;
            None
        }
        started = &mut signal_seen => started.ok().map(|started| started + options.drain_timeout),
    };
    if let Some(deadline) = deadline {
        // Past the deadline, calls still in flight (a client that never reads its stream, a health
        // Watch) are dropped with their connections.
        match tokio::time::timeout_at(deadline, &mut server).await {
            Ok(result) => result?,
            Err(_) => warn!("shutting down: calls still in flight at the drain deadline were dropped"),
        }
    }
    reaper.abort();
    snapshots.abort();
    if let Some(health_only) = health_only {
        health_only.abort();
    }
    let closing = manager.shutdown();
    match deadline {
        Some(deadline) => {
            if tokio::time::timeout_at(deadline.max(tokio::time::Instant::now() + Duration::from_secs(1)), closing).await.is_err() {
                warn!("shutting down: sessions still closing at the drain deadline were left to the workers' exit");
            }
        }
        None => closing.await,
    }
    info!("stopped");
    Ok(())
}
