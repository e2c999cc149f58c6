//! The radserve server, assembled: the simulator core behind the gRPC service, with health checking,
//! reflection and graceful shutdown. `main.rs` is the command line around it.

pub mod augment_cli;
pub mod config;

use std::future::Future;
use std::path::PathBuf;
use std::sync::Arc;

use radserve_service::{proto::FILE_DESCRIPTOR_SET, RadServeServer, RadServeService, MAX_MESSAGE_BYTES};
use radserve_sim::{GlBackend, Limits, SessionManager, WorkerLauncher, WorkerPool};
use tokio::net::TcpListener;
use tonic::transport::server::TcpIncoming;
use tracing::info;

/// Everything the server needs to start its workers.
pub struct ServerSettings {
    /// The executable started in `worker` mode (normally this very binary).
    pub worker_program: PathBuf,
    pub venv: PathBuf,
    pub gl: GlBackend,
    pub workers: usize,
    pub limits: Limits,
}

pub fn session_manager(settings: ServerSettings) -> Arc<SessionManager> {
    let launcher = WorkerLauncher { program: settings.worker_program, venv: settings.venv, gl: settings.gl };
    let pool = WorkerPool::start(launcher, settings.workers);
    Arc::new(SessionManager::new(pool, settings.limits))
}

/// Serves on `listener` until `shutdown` resolves; then reports NOT_SERVING, stops accepting, drains
/// the calls in flight and closes every session.
pub async fn serve(
    listener: TcpListener,
    manager: Arc<SessionManager>,
    augment_threads: usize,
    shutdown: impl Future<Output = ()> + Send,
) -> anyhow::Result<()> {
    // Minibatch augmentation runs here, never on tokio's workers; 0 threads: one per core.
    let augment_pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(augment_threads)
            .thread_name(|index| format!("radserve-augment-{index}"))
            .build()?,
    );
    let (health_reporter, health_service) = tonic_health::server::health_reporter();
    health_reporter.set_serving::<RadServeServer<RadServeService>>().await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let service = RadServeServer::new(RadServeService::new(manager.clone(), augment_pool))
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);

    // Learn the env names in the background so the first CreateSession does not wait for them, and the
    // catalog after them.
    let warm = manager.clone();
    tokio::spawn(async move {
        if let Err(error) = warm.catalog().await {
            tracing::warn!(%error, "could not build the environment catalog");
        }
    });

    // Sessions whose lease expired (a learner that died without closing them) are closed here.
    let reaper = tokio::spawn(manager.clone().run_reaper());

    let reporter = health_reporter.clone();
    let graceful = async move {
        shutdown.await;
        info!("shutting down: not serving, draining calls");
        reporter.set_not_serving::<RadServeServer<RadServeService>>().await;
    };
    tonic::transport::Server::builder()
        .add_service(health_service)
        .add_service(reflection)
        .add_service(service)
        // Small request/response pairs (acting) stall ~40 ms on Nagle + delayed ACK without NODELAY.
        .serve_with_incoming_shutdown(TcpIncoming::from(listener).with_nodelay(Some(true)), graceful)
        .await?;
    reaper.abort();
    manager.shutdown().await;
    info!("stopped");
    Ok(())
}
