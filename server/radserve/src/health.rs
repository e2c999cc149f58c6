//! What grpc.health.v1 answers (docs/operations.md "Health"): the whole server ("") SERVING once the
//! environment catalog is built and until shutdown begins; the RadServe and dm_env_rpc services the
//! same, and also NOT_SERVING while a simulator worker is stuck in a call. One state, published whole
//! under a lock, so that the catalog task, the stuck-worker watch and the shutdown never interleave
//! into a status none of them meant.

use std::sync::Arc;
use std::time::Duration;

use radserve_core::SessionManager;
use radserve_service::{EnvironmentServer, EnvironmentService, RadServeServer, RadServeService};
use tonic::server::NamedService;
use tonic_health::server::HealthReporter;
use tonic_health::ServingStatus;
use tracing::{info, warn};

#[derive(Default)]
struct State {
    catalog_ready: bool,
    stuck: bool,
    draining: bool,
}

/// The server's health, as its reporter publishes it.
pub(crate) struct Health {
    reporter: HealthReporter,
    state: tokio::sync::Mutex<State>,
}

impl Health {
    /// Starts NOT_SERVING everywhere (the catalog is not built yet).
    pub(crate) async fn new(reporter: HealthReporter) -> Arc<Health> {
        let health = Arc::new(Health { reporter, state: tokio::sync::Mutex::new(State::default()) });
        health.update(|_| {}).await;
        health
    }

    async fn update(&self, change: impl FnOnce(&mut State)) {
        let mut state = self.state.lock().await;
        change(&mut state);
        let status = |serving: bool| if serving { ServingStatus::Serving } else { ServingStatus::NotServing };
        let whole = status(state.catalog_ready && !state.draining);
        let services = status(state.catalog_ready && !state.draining && !state.stuck);
        self.reporter.set_service_status("", whole).await;
        self.reporter.set_service_status(<RadServeServer<RadServeService> as NamedService>::NAME, services).await;
        self.reporter.set_service_status(<EnvironmentServer<EnvironmentService> as NamedService>::NAME, services).await;
    }

    /// Shutdown began: NOT_SERVING everywhere, for good.
    pub(crate) async fn drain(&self) {
        self.update(|state| state.draining = true).await;
    }

    /// Builds the catalog (the env names first, which a first CreateSession waits for, then every
    /// env's spec) and reports SERVING once it is built. A failure is logged and tried again, with a
    /// backoff up to a minute, NOT_SERVING meanwhile: a server whose simulators cannot list their
    /// envs is not ready, and an orchestrator's startup probe restarts it in the end.
    pub(crate) async fn build_catalog(self: Arc<Self>, manager: Arc<SessionManager>) {
        let started = tokio::time::Instant::now();
        let mut backoff = Duration::from_secs(1);
        loop {
            match manager.catalog().await {
                Ok(entries) => {
                    info!(envs = entries.len(), seconds = started.elapsed().as_secs_f64(), "environment catalog built: SERVING");
                    self.update(|state| state.catalog_ready = true).await;
                    return;
                }
                Err(error) => {
                    warn!(%error, retry_s = backoff.as_secs_f64(), "could not build the environment catalog: NOT_SERVING, trying again");
                    tokio::time::sleep(backoff).await;
                    backoff = (backoff * 2).min(Duration::from_secs(60));
                }
            }
        }
    }

    /// Reports the RadServe and dm_env_rpc services NOT_SERVING while a simulator worker has been in
    /// one call for longer than `after` (stuck: its sessions' calls wait for it until its deadline
    /// kills it), and SERVING again once none is. Checked a few times per `after`, at most once per
    /// 100 ms.
    pub(crate) async fn watch_stuck_workers(self: Arc<Self>, manager: Arc<SessionManager>, after: Duration) {
        let period = (after / 4).clamp(Duration::from_millis(100), Duration::from_secs(2));
        let mut stuck = false;
        loop {
            tokio::time::sleep(period).await;
            let overdue = manager.overdue_simulators(after);
            if overdue.is_empty() != stuck {
                continue; // unchanged
            }
            stuck = !overdue.is_empty();
            if stuck {
                warn!(workers = ?overdue, after_s = after.as_secs_f64(), "a simulator worker is stuck in a call: RadServe and dm_env_rpc NOT_SERVING");
            } else {
                info!("no simulator worker is stuck any more: RadServe and dm_env_rpc SERVING");
            }
            self.update(|state| state.stuck = stuck).await;
        }
    }
}
