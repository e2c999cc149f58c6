//! The Prometheus endpoint: `GET /metrics` on its own port (`metrics.address`, off by default), in
//! the OpenMetrics text format, encoded by the Prometheus project's Rust client (prometheus-client)
//! and served by hyper (already in the tree through tonic).
//!
//! Everything is read at scrape time: counters and the step-latency histogram from the core's
//! atomics (`radserve_core::metrics`), gauges from the session registry, the memory budget and the
//! worker pool. Counters are monotonic over the server's life (sessions that closed still count).

use std::convert::Infallible;
use std::sync::Arc;

use http_body_util::Full;
use hyper::body::{Bytes, Incoming};
use hyper::{Method, Request, Response, StatusCode};
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric, MetricEncoder, NoLabelSet};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::info::Info;
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::Registry;
use radserve_core::metrics::HistogramSnapshot;
use radserve_core::{Family, Principal, SessionManager};
use radserve_sim::WorkerPool;
use tokio::net::TcpListener;
use tracing::{debug, warn};

/// The content type of the OpenMetrics text format (Prometheus scrapes it natively).
const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// What the endpoint reads.
#[derive(Clone)]
pub struct Sources {
    pub manager: Arc<SessionManager>,
    /// The simulator workers (None over the fake simulators of the tests).
    pub workers: Option<Arc<WorkerPool>>,
}

impl std::fmt::Debug for Sources {
    fn fmt(&self, formatter: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        formatter.debug_struct("Sources").finish_non_exhaustive()
    }
}

/// The step-latency histogram as prometheus-client encodes one.
struct Histogram(HistogramSnapshot);

impl EncodeMetric for Histogram {
    fn encode(&self, mut encoder: MetricEncoder) -> Result<(), std::fmt::Error> {
        encoder.encode_histogram::<NoLabelSet>(self.0.sum_seconds, self.0.count, &self.0.buckets, None)
    }

    fn metric_type(&self) -> MetricType {
        MetricType::Histogram
    }
}

fn family_label(family: Family) -> [(&'static str, &'static str); 1] {
    [("family", family.prefix())]
}

impl Collector for Sources {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let core = self.manager.metrics();
        let sessions = self.manager.list_sessions(&Principal::local());

        // OpenMetrics' info type: exposed as radserve_build_info{version="..."} 1.
        Info::new(vec![("version", radserve_service::VERSION), ("api", radserve_service::API)])
            .encode(encoder.encode_descriptor("radserve_build", "The server's release and the gRPC API it implements", None, MetricType::Info)?)?;

        let mut steps = encoder.encode_descriptor("radserve_env_steps", "Environment steps (each env of a Step counts one)", None, MetricType::Counter)?;
        for (family, count) in core.env_steps() {
            ConstCounter::new(count).encode(steps.encode_family(&family_label(family))?)?;
        }
        let counters = [
            ("radserve_episodes", "Episodes ended", core.episodes()),
            ("radserve_simulator_errors", "Episodes ended by a simulator that raised or a worker that died or hung", core.simulator_errors()),
            ("radserve_resets", "Reset calls", core.resets()),
            ("radserve_batches", "Augmented minibatches sent to learners", core.batches()),
        ];
        for (name, help, value) in counters {
            ConstCounter::new(value).encode(encoder.encode_descriptor(name, help, None, MetricType::Counter)?)?;
        }
        let snapshots = core.snapshots();
        let load = |counter: &std::sync::atomic::AtomicU64| counter.load(std::sync::atomic::Ordering::Relaxed);
        let snapshot_counters = [
            ("radserve_snapshots", "Replay snapshots of named sessions written", load(&snapshots.written)),
            ("radserve_snapshot_bytes", "Bytes of replay snapshots written", load(&snapshots.bytes)),
            ("radserve_snapshot_failures", "Replay snapshots that could not be written, or read when a named session was created", load(&snapshots.failures)),
            ("radserve_snapshot_restores", "Named sessions whose replay was restored from a snapshot", load(&snapshots.restores)),
            ("radserve_snapshot_restored_transitions", "Transitions restored from snapshots", load(&snapshots.restored_transitions)),
            ("radserve_actor_env_steps", "Environment steps taken by server-side actors (random warm-up steps included)", load(&core.acting.env_steps)),
            ("radserve_actor_policies", "Policies loaded by SetPolicy", load(&core.acting.policies)),
            ("radserve_actor_failures", "Server-side actors stopped by an error (a policy output that is not finite, envs failing step after step)", load(&core.acting.failures)),
        ];
        for (name, help, value) in snapshot_counters {
            ConstCounter::new(value).encode(encoder.encode_descriptor(name, help, None, MetricType::Counter)?)?;
        }
        for (name, help, nanos) in [
            ("radserve_snapshot_duration_seconds", "Time spent writing replay snapshots (paced by replay.snapshot_bytes_per_second)", &snapshots.nanos),
            ("radserve_snapshot_restore_duration_seconds", "Time spent restoring replay from snapshots", &snapshots.restore_nanos),
            ("radserve_actor_inference_seconds", "Time server-side actors spent in policy inference", &core.acting.inference_nanos),
        ] {
            ConstCounter::new(load(nanos) as f64 / 1e9).encode(encoder.encode_descriptor(name, help, None, MetricType::Counter)?)?;
        }
        let restarts = self.workers.as_ref().map_or(0, |pool| pool.workers().iter().map(|worker| worker.restarts()).sum());
        ConstCounter::new(restarts).encode(encoder.encode_descriptor(
            "radserve_worker_restarts",
            "Simulator worker processes replaced after dying or hanging",
            None,
            MetricType::Counter,
        )?)?;
        Histogram(core.step_seconds()).encode(encoder.encode_descriptor(
            "radserve_step_seconds",
            "Time of a Step call in the core (all its envs, workers included)",
            None,
            MetricType::Histogram,
        )?)?;

        let gauge = |value: u64| ConstGauge::new(i64::try_from(value).unwrap_or(i64::MAX));
        let mut envs = encoder.encode_descriptor("radserve_envs", "Environments in open sessions", None, MetricType::Gauge)?;
        for family in Family::ALL {
            let count: usize = sessions
                .iter()
                .filter(|session| session.env_id.split('/').next() == Some(family.prefix()))
                .map(|session| session.num_envs)
                .sum();
            gauge(count as u64).encode(envs.encode_family(&family_label(family))?)?;
        }
        let (used, budget) = self.manager.memory();
        let gauges = [
            ("radserve_sessions", "Open sessions", sessions.len() as u64),
            ("radserve_open_streams", "Streams holding a session open (sample streams, shared-stepping channels, joined dm_env_rpc streams)", sessions.iter().map(|s| s.open_streams as u64).sum()),
            ("radserve_replay_transitions", "Transitions held by the open sessions' replay buffers", sessions.iter().map(|s| s.replay_transitions).sum()),
            ("radserve_replay_bytes", "Memory of the open sessions' replay buffers", sessions.iter().map(|s| s.replay_bytes).sum()),
            ("radserve_snapshot_disk_bytes", "Bytes the open named sessions' replay snapshots take on disk", sessions.iter().filter_map(|s| s.snapshot.as_ref()).map(|s| s.disk_bytes).sum()),
            ("radserve_snapshot_age_seconds", "Age of the oldest replay snapshot of an open named session (0: none)", sessions.iter().filter_map(|s| s.snapshot.as_ref()?.age).max().map_or(0, |age| age.as_secs())),
            ("radserve_memory_used_bytes", "Memory reserved against the budget (limits.memory_bytes)", used),
            ("radserve_memory_budget_bytes", "The memory budget", budget),
            ("radserve_workers", "Simulator worker processes", self.workers.as_ref().map_or(0, |pool| pool.len() as u64)),
        ];
        for (name, help, value) in gauges {
            gauge(value).encode(encoder.encode_descriptor(name, help, None, MetricType::Gauge)?)?;
        }
        Ok(())
    }
}

/// The OpenMetrics text of one scrape.
pub fn render(sources: &Sources) -> Result<String, std::fmt::Error> {
    let mut registry = Registry::default();
    registry.register_collector(Box::new(sources.clone()));
    let mut text = String::new();
    prometheus_client::encoding::text::encode(&mut text, &registry)?;
    Ok(text)
}

fn respond(status: StatusCode, content_type: &str, body: String) -> Response<Full<Bytes>> {
    Response::builder()
        .status(status)
        .header(hyper::header::CONTENT_TYPE, content_type)
        .body(Full::new(Bytes::from(body)))
        .expect("a valid response")
}

async fn answer(sources: Sources, request: Request<Incoming>) -> Result<Response<Full<Bytes>>, Infallible> {
    let text = "text/plain; charset=utf-8";
    Ok(match (request.method(), request.uri().path()) {
        (&Method::GET, "/metrics") => match render(&sources) {
            Ok(body) => respond(StatusCode::OK, CONTENT_TYPE, body),
            Err(_) => respond(StatusCode::INTERNAL_SERVER_ERROR, text, "encoding the metrics failed\n".into()),
        },
        (_, "/metrics") => respond(StatusCode::METHOD_NOT_ALLOWED, text, "GET /metrics\n".into()),
        _ => respond(StatusCode::NOT_FOUND, text, "radserve serves its metrics at /metrics\n".into()),
    })
}

/// Serves `/metrics` on `listener` until the task is dropped.
pub async fn serve(listener: TcpListener, sources: Sources) {
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(error) => {
                warn!(%error, "metrics: accepting a connection failed");
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                continue;
            }
        };
        let sources = sources.clone();
        tokio::spawn(async move {
            let service = hyper::service::service_fn(move |request| answer(sources.clone(), request));
            let connection = hyper::server::conn::http1::Builder::new()
                .serve_connection(hyper_util::rt::TokioIo::new(stream), service);
            // A scraper that stalls is dropped with its connection after this long.
            if let Ok(Err(error)) = tokio::time::timeout(std::time::Duration::from_secs(30), connection).await {
                debug!(%error, %peer, "metrics connection ended");
            }
        });
    }
}
