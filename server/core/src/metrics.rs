//! What the server has done since it started, for operators: monotonic counters and a step-latency
//! histogram, kept in atomics on the paths that do the work (a step, a batch) and read by the
//! binary's Prometheus endpoint at scrape time. The core depends on no metrics library: the binary
//! encodes these (`radserve::metrics`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use crate::catalog::Family;

/// Upper bounds (seconds) of the step-latency buckets: a Step call's time in the core, from a
/// ProcGen step of a few envs (~0.1 ms) to a dm_control pixel step of many (~1 s).
pub const STEP_SECONDS_BUCKETS: [f64; 14] =
    [0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5];

#[derive(Debug, Default)]
pub struct CoreMetrics {
    /// Env steps by family (`Family::ALL` order): each env of a Step call counts one.
    env_steps: [AtomicU64; 3],
    episodes: AtomicU64,
    /// Episodes ended by a simulator that raised or a worker that died or hung.
    simulator_errors: AtomicU64,
    resets: AtomicU64,
    /// Minibatches sent to learners (both deliveries).
    batches: AtomicU64,
    step_seconds: Histogram,
    snapshots: SnapshotCounters,
    pub acting: ActingCounters,
}

/// Server-side actors since the server started.
#[derive(Debug, Default)]
pub struct ActingCounters {
    /// Env steps the actors took (each env of a step counts one; random warm-up steps included).
    pub env_steps: AtomicU64,
    /// Policies loaded (SetPolicy calls that succeeded).
    pub policies: AtomicU64,
    /// Actors stopped by an error (a policy output that is not finite, envs failing in a row).
    pub failures: AtomicU64,
    pub inference_nanos: AtomicU64,
}

impl ActingCounters {
    pub fn add_inference(&self, seconds: f64) {
        self.inference_nanos.fetch_add((seconds * 1e9) as u64, Ordering::Relaxed);
    }
}

/// Named sessions' replay snapshots since the server started.
#[derive(Debug, Default)]
pub struct SnapshotCounters {
    pub written: AtomicU64,
    pub bytes: AtomicU64,
    pub nanos: AtomicU64,
    pub failures: AtomicU64,
    pub restores: AtomicU64,
    pub restored_transitions: AtomicU64,
    pub restore_nanos: AtomicU64,
}

fn nanos(elapsed: Duration) -> u64 {
    u64::try_from(elapsed.as_nanos()).unwrap_or(u64::MAX)
}

/// A histogram over [`STEP_SECONDS_BUCKETS`]: per-bucket counts (the last bucket is +Inf), the sum
/// in nanoseconds and the count.
#[derive(Debug, Default)]
pub struct Histogram {
    buckets: [AtomicU64; STEP_SECONDS_BUCKETS.len() + 1],
    sum_nanos: AtomicU64,
    count: AtomicU64,
}

/// A histogram as read at one moment: (upper bound, count in that bucket) with +Inf last as
/// `f64::MAX`, the sum in seconds and the count.
#[derive(Clone, Debug, PartialEq)]
pub struct HistogramSnapshot {
    pub buckets: Vec<(f64, u64)>,
    pub sum_seconds: f64,
    pub count: u64,
}

impl Histogram {
    pub fn observe(&self, elapsed: Duration) {
        let seconds = elapsed.as_secs_f64();
        let bucket = STEP_SECONDS_BUCKETS.iter().position(|&bound| seconds <= bound).unwrap_or(STEP_SECONDS_BUCKETS.len());
        self.buckets[bucket].fetch_add(1, Ordering::Relaxed);
        self.sum_nanos.fetch_add(u64::try_from(elapsed.as_nanos()).unwrap_or(u64::MAX), Ordering::Relaxed);
        self.count.fetch_add(1, Ordering::Relaxed);
    }

    pub fn snapshot(&self) -> HistogramSnapshot {
        let bounds = STEP_SECONDS_BUCKETS.iter().copied().chain([f64::MAX]);
        HistogramSnapshot {
            buckets: bounds.zip(&self.buckets).map(|(bound, count)| (bound, count.load(Ordering::Relaxed))).collect(),
            sum_seconds: self.sum_nanos.load(Ordering::Relaxed) as f64 / 1e9,
            count: self.count.load(Ordering::Relaxed),
        }
    }
}

fn family_index(family: Family) -> usize {
    Family::ALL.iter().position(|&each| each == family).expect("Family::ALL lists every family")
}

impl CoreMetrics {
    /// One Step call: `envs` env steps of `family` in `elapsed`, `episodes` ended, `errors` of
    /// them by a simulator error.
    pub fn record_step(&self, family: Family, envs: u64, elapsed: Duration, episodes: u64, errors: u64) {
        self.env_steps[family_index(family)].fetch_add(envs, Ordering::Relaxed);
        self.episodes.fetch_add(episodes, Ordering::Relaxed);
        self.simulator_errors.fetch_add(errors, Ordering::Relaxed);
        self.step_seconds.observe(elapsed);
    }

    pub fn record_reset(&self) {
        self.resets.fetch_add(1, Ordering::Relaxed);
    }

    pub fn record_batch(&self) {
        self.batches.fetch_add(1, Ordering::Relaxed);
    }

    /// Env steps so far by family, in `Family::ALL` order.
    pub fn env_steps(&self) -> [(Family, u64); 3] {
        Family::ALL.map(|family| (family, self.env_steps[family_index(family)].load(Ordering::Relaxed)))
    }

    pub fn episodes(&self) -> u64 {
        self.episodes.load(Ordering::Relaxed)
    }

    pub fn simulator_errors(&self) -> u64 {
        self.simulator_errors.load(Ordering::Relaxed)
    }

    pub fn resets(&self) -> u64 {
        self.resets.load(Ordering::Relaxed)
    }

    pub fn batches(&self) -> u64 {
        self.batches.load(Ordering::Relaxed)
    }

    /// A snapshot written: its bytes and how long it took.
    pub fn record_snapshot(&self, bytes: u64, elapsed: Duration) {
        self.snapshots.written.fetch_add(1, Ordering::Relaxed);
        self.snapshots.bytes.fetch_add(bytes, Ordering::Relaxed);
        self.snapshots.nanos.fetch_add(nanos(elapsed), Ordering::Relaxed);
    }

    /// A snapshot that could not be written, or read at creation.
    pub fn record_snapshot_failure(&self) {
        self.snapshots.failures.fetch_add(1, Ordering::Relaxed);
    }

    /// A replay restored from its snapshot.
    pub fn record_restore(&self, transitions: u64, elapsed: Duration) {
        self.snapshots.restores.fetch_add(1, Ordering::Relaxed);
        self.snapshots.restored_transitions.fetch_add(transitions, Ordering::Relaxed);
        self.snapshots.restore_nanos.fetch_add(nanos(elapsed), Ordering::Relaxed);
    }

    pub fn snapshots(&self) -> &SnapshotCounters {
        &self.snapshots
    }

    pub fn step_seconds(&self) -> HistogramSnapshot {
        self.step_seconds.snapshot()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steps_land_in_their_bucket_and_family() {
        let metrics = CoreMetrics::default();
        metrics.record_step(Family::Gym, 8, Duration::from_micros(300), 2, 1);
        metrics.record_step(Family::Gym, 8, Duration::from_secs(10), 0, 0);
        metrics.record_step(Family::Dmc, 1, Duration::from_micros(100), 0, 0);
        assert_eq!(metrics.env_steps(), [(Family::Dmc, 1), (Family::Gym, 16), (Family::Procgen, 0)]);
        assert_eq!((metrics.episodes(), metrics.simulator_errors()), (2, 1));
        let snapshot = metrics.step_seconds();
        assert_eq!(snapshot.count, 3);
        let count = |bound: f64| snapshot.buckets.iter().find(|(b, _)| *b == bound).unwrap().1;
        assert_eq!((count(0.0001), count(0.0005), count(f64::MAX)), (1, 1, 1), "100 us is <= 0.0001 s: bounds are inclusive");
        assert!((snapshot.sum_seconds - 10.0004).abs() < 1e-9);
    }
}
