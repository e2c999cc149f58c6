//! Named sessions and their replay snapshots: with `[replay] snapshot_dir` set, the replay buffer of
//! each named session is written to `<snapshot_dir>/<owner, hex>/<name>/` in the background (the
//! frames recorded since the last snapshot, paced to `snapshot_bytes_per_second`), once more when the
//! session closes or the server shuts down, and read back when the same owner creates a session of
//! the same name, env id and options after a restart (`radserve_replay::snapshot` has the format).

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex as StdMutex, RwLock};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use radserve_replay::snapshot::{self, RestoreReport, SessionCounters, SnapshotError, SnapshotPath, SnapshotWriter, Throttle};
use radserve_replay::{BufferKind, ReplayBuffer};
use serde::{Deserialize, Serialize};
use tracing::{info, warn};

use super::{Entry, SessionManager};
use crate::error::CoreError;
use crate::metrics::CoreMetrics;
use crate::principal::log_id;
use crate::session::{Session, SessionStats};

/// The `[replay]` section: where and how often named sessions' replay buffers are snapshotted.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct ReplayConfig {
    /// Directory for the replay snapshots of named sessions (`CreateSession.name`), one directory
    /// per owner and name; a named session created again after a restart restores its replay from
    /// it. Unset: no snapshots (a restart loses every replay buffer).
    pub snapshot_dir: Option<PathBuf>,
    /// Seconds between two snapshots of a session. Each writes only the transitions recorded since
    /// the previous one (and, once the files reach twice the buffer, every transition once).
    pub snapshot_interval_s: f64,
    /// Bytes per second all snapshots together may write (0: as fast as the disk takes them), so a
    /// snapshot does not take the disk or the memory bandwidth from stepping and sampling. A session's
    /// final snapshot (at close or shutdown) is not paced.
    pub snapshot_bytes_per_second: u64,
    /// A snapshot that cannot be used (damaged, truncated, of another format version, or of a
    /// session created with other options): "empty" moves it aside (`<name>.rejected-<time>`) and
    /// starts the session with an empty buffer; "refuse" refuses CreateSession (FAILED_PRECONDITION)
    /// and leaves the files as they are.
    pub on_bad_snapshot: OnBadSnapshot,
}

impl Default for ReplayConfig {
    fn default() -> Self {
        ReplayConfig {
            snapshot_dir: None,
            snapshot_interval_s: 60.0,
            snapshot_bytes_per_second: 256 << 20,
            on_bad_snapshot: OnBadSnapshot::Empty,
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum OnBadSnapshot {
    #[default]
    Empty,
    Refuse,
}

/// The most bytes of a session name.
pub const MAX_NAME_BYTES: usize = 64;

/// A name is a file name on every system: letters, digits, `.`, `_` and `-`, not starting with `.`.
pub(crate) fn check_name(name: &str) -> Result<(), CoreError> {
    let valid = !name.is_empty()
        && name.len() <= MAX_NAME_BYTES
        && !name.starts_with('.')
        && name.bytes().all(|byte| byte.is_ascii_alphanumeric() || matches!(byte, b'.' | b'_' | b'-'));
    if valid {
        Ok(())
    } else {
        Err(CoreError::InvalidSession(format!(
            "session name {:?}: give 1 to {MAX_NAME_BYTES} letters, digits, '.', '_' or '-', not starting with '.'",
            crate::bounds::clip(name)
        )))
    }
}

/// A named session's snapshot: its writer, and when it last succeeded.
pub(crate) struct SnapshotSlot {
    writer: StdMutex<SnapshotWriter>,
    /// Milliseconds since the Unix epoch of the last snapshot that landed (or of the restored one).
    last_success_unix_ms: AtomicU64,
    /// Bytes of the snapshot on disk, and the frames it covers (kept here: reading the writer's
    /// would wait for a write in progress).
    disk_bytes: AtomicU64,
    covered_frames: AtomicU64,
    /// Transitions the session's buffer got back from its snapshot at creation.
    pub(crate) restored_transitions: u64,
    /// Set (under the writer's lock) once the session closed and its last snapshot is written: a
    /// pass that took the session before it closed writes nothing after that, since a session
    /// created again under the name may already be restoring from the same directory.
    closed: AtomicBool,
}

impl SnapshotSlot {
    /// How old the snapshot on disk is (None: none was written yet).
    pub(crate) fn age(&self) -> Option<Duration> {
        let last = self.last_success_unix_ms.load(Ordering::Relaxed);
        (last > 0).then(|| Duration::from_millis(unix_ms().saturating_sub(last)))
    }

    /// What Describe shows of it, as of `replay` (the buffer it snapshots).
    pub(crate) fn info(&self, replay: &RwLock<ReplayBuffer>) -> super::SnapshotInfo {
        let frames_written = replay.read().expect("replay lock").frames_written();
        super::SnapshotInfo {
            restored_transitions: self.restored_transitions,
            disk_bytes: self.disk_bytes.load(Ordering::Relaxed),
            age: self.age(),
            pending_frames: frames_written.saturating_sub(self.covered_frames.load(Ordering::Relaxed)),
        }
    }
}

fn unix_ms() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |since| since.as_millis() as u64)
}

/// What the manager keeps for snapshots.
pub(crate) struct Snapshots {
    pub(crate) config: ReplayConfig,
    /// Set at shutdown: a paced snapshot in progress finishes at full speed.
    hurry: Arc<AtomicBool>,
}

impl Snapshots {
    pub(crate) fn new(config: ReplayConfig) -> Option<Snapshots> {
        config.snapshot_dir.is_some().then(|| Snapshots { config, hurry: Arc::default() })
    }

    /// `<snapshot_dir>/<owner, hex>/<name>`, opened below `snapshot_dir` without following a symlink.
    fn dir(&self, owner: &str, name: &str) -> Result<SnapshotPath, CoreError> {
        let root = self.config.snapshot_dir.as_ref().expect("snapshots have a directory");
        SnapshotPath::new(root, &[&owner_dir(owner), name]).map_err(|error| CoreError::Host(format!("the snapshot directory of '{name}': {error}")))
    }
}

/// The directory of an owner's snapshots under `snapshot_dir`: its name in hex (a principal's name may
/// hold any character).
pub(crate) fn owner_dir(owner: &str) -> String {
    owner.bytes().map(|byte| format!("{byte:02x}")).collect()
}

/// What a session was created as: a snapshot is restored only into the same.
fn identity(session: &Session) -> String {
    let options: Vec<String> = session.config.options.iter().map(|(key, value)| format!("{key}={value}")).collect();
    format!(
        "env {} with {} envs, frame_stack {}, options {{{}}}",
        session.config.env.full(),
        session.num_envs(),
        session.config.frame_stack,
        options.join(", ")
    )
}

impl SessionManager {
    /// Snapshot named sessions' replay buffers as `config` says (nothing when it has no directory).
    pub fn with_snapshots(mut self, config: ReplayConfig) -> Self {
        self.snapshots = Snapshots::new(config);
        self
    }

    /// For a named session with a replay buffer on a server that snapshots: its snapshot, restored into
    /// the buffer if one exists. A snapshot that cannot be used is set aside or refused as configured.
    pub(super) async fn open_snapshot(&self, session: &mut Session, owner: &str, name: &str) -> Result<Option<Arc<SnapshotSlot>>, CoreError> {
        let Some(snapshots) = &self.snapshots else { return Ok(None) };
        let Some(replay) = session.replay().cloned() else { return Ok(None) };
        if replay.read().expect("replay lock").layout().kind != BufferKind::Replay {
            return Ok(None);
        }
        let (dir, identity) = (snapshots.dir(owner, name)?, identity(session));
        let policy = snapshots.config.on_bad_snapshot;
        let metrics = self.metrics.clone();
        let counted = metrics.clone();
        let opened = tokio::task::spawn_blocking(move || restore_or_start(&replay, &dir, &identity, policy, &counted))
            .await
            .map_err(|error| CoreError::Host(format!("the snapshot restore did not finish: {error}")))?;
        let (writer, restored) = match opened {
            Ok(opened) => opened,
            Err(error) => {
                return Err(CoreError::BadSnapshot(format!(
                    "session '{name}' has a snapshot this server cannot restore (replay.on_bad_snapshot = \"refuse\"): \
                     {error}; fix or remove it, or create the session under another name"
                )));
            }
        };
        let mut restored_transitions = 0;
        let mut last_success_unix_ms = 0;
        if let Some(report) = restored {
            metrics.record_restore(report.transitions as u64, report.duration);
            restored_transitions = report.transitions as u64;
            last_success_unix_ms = unix_ms().saturating_sub(report.age.as_millis() as u64).max(1);
            session.continue_from(report.session);
            info!(
                name,
                transitions = report.transitions,
                truncated_episodes = report.truncated_episodes,
                mib = report.bytes >> 20,
                seconds = report.duration.as_secs_f64(),
                age_s = report.age.as_secs(),
                "replay restored from its snapshot"
            );
        }
        Ok(Some(Arc::new(SnapshotSlot {
            disk_bytes: AtomicU64::new(writer.disk_bytes()),
            covered_frames: AtomicU64::new(writer.covered_frames()),
            writer: StdMutex::new(writer),
            last_success_unix_ms: AtomicU64::new(last_success_unix_ms),
            restored_transitions,
            closed: AtomicBool::new(false),
        })))
    }

    /// One snapshot of every named session that recorded something since its last, paced to the
    /// configured rate over the whole pass.
    pub fn snapshot_all(&self, paced: bool) {
        let Some(snapshots) = &self.snapshots else { return };
        let entries: Vec<Snapshotted> = {
            let registry = self.sessions.lock().expect("registry lock");
            registry.sessions.iter().filter_map(|(id, entry)| Snapshotted::of(id, entry)).collect()
        };
        let rate = if paced { snapshots.config.snapshot_bytes_per_second } else { 0 };
        let mut throttle = Throttle::new(rate, Some(snapshots.hurry.clone()));
        for entry in entries {
            entry.write(&self.metrics, &mut throttle);
        }
    }

    /// Snapshots named sessions every `snapshot_interval_s` until the server shuts down.
    pub async fn run_snapshots(self: Arc<Self>) {
        let Some(snapshots) = &self.snapshots else { return };
        let period = Duration::from_secs_f64(snapshots.config.snapshot_interval_s.max(0.05));
        loop {
            tokio::time::sleep(period).await;
            if self.sessions.lock().expect("registry lock").closing {
                return;
            }
            let manager = self.clone();
            if tokio::task::spawn_blocking(move || manager.snapshot_all(true)).await.is_err() {
                warn!("a snapshot pass panicked");
            }
        }
    }

    /// A closing session's last snapshot (not paced), or its snapshot removed when its owner asked.
    pub(super) async fn final_snapshot(&self, session_id: &str, entry: &Entry, discard: bool) {
        let Some(entry) = Snapshotted::of(session_id, entry) else { return };
        let metrics = self.metrics.clone();
        let done = tokio::task::spawn_blocking(move || {
            if !discard {
                entry.write(&metrics, &mut Throttle::new(0, None));
            }
            let writer = entry.slot.writer.lock().expect("snapshot writer lock");
            entry.slot.closed.store(true, Ordering::Relaxed);
            if discard {
                if let Err(error) = writer.discard() {
                    warn!(session = log_id(&entry.session_id), %error, dir = %writer.dir().display(), "could not remove the session's snapshot");
                }
            }
        })
        .await;
        if done.is_err() {
            warn!("a session's final snapshot panicked");
        }
    }

    /// Asks a paced snapshot in progress to finish at full speed (the server is stopping).
    pub(super) fn hurry_snapshots(&self) {
        if let Some(snapshots) = &self.snapshots {
            snapshots.hurry.store(true, Ordering::Relaxed);
        }
    }
}

/// A session to snapshot: what a snapshot reads, taken out of the registry.
struct Snapshotted {
    session_id: String,
    slot: Arc<SnapshotSlot>,
    replay: Arc<RwLock<ReplayBuffer>>,
    stats: Arc<SessionStats>,
}

impl Snapshotted {
    fn of(session_id: &str, entry: &Entry) -> Option<Snapshotted> {
        Some(Snapshotted {
            session_id: session_id.to_string(),
            slot: entry.snapshot.clone()?,
            replay: entry.replay.clone()?,
            stats: entry.stats.clone(),
        })
    }

    /// One snapshot, if the session recorded anything since its last; a failure is logged and
    /// counted, and the next snapshot writes the same frames again.
    fn write(&self, metrics: &CoreMetrics, throttle: &mut Throttle) {
        let mut writer = self.slot.writer.lock().expect("snapshot writer lock");
        if self.slot.closed.load(Ordering::Relaxed) {
            return;
        }
        let (pending, steps) = {
            let buffer = self.replay.read().expect("replay lock");
            (writer.pending_frames(&buffer), buffer.steps_recorded())
        };
        if pending == 0 && writer.written() {
            return;
        }
        let counters = SessionCounters {
            step_calls: steps,
            total_env_steps: self.stats.total_env_steps.load(Ordering::Relaxed),
            episodes_completed: self.stats.episodes_completed.load(Ordering::Relaxed),
        };
        match writer.write(&self.replay, counters, throttle) {
            Ok(report) => {
                self.slot.last_success_unix_ms.store(unix_ms(), Ordering::Relaxed);
                self.slot.disk_bytes.store(report.disk_bytes, Ordering::Relaxed);
                self.slot.covered_frames.store(writer.covered_frames(), Ordering::Relaxed);
                metrics.record_snapshot(report.bytes, report.duration);
            }
            Err(error) => {
                metrics.record_snapshot_failure();
                warn!(
                    session = log_id(&self.session_id),
                    %error,
                    "replay snapshot failed; the previous one stays valid and the next try writes these frames again"
                );
            }
        }
    }
}

/// Reads the snapshot in `dir` into `replay` (or starts a new one): the writer, and what was restored.
/// A snapshot that cannot be used is counted as a failure, then set aside with a warning (policy
/// "empty") or returned as the error ("refuse").
fn restore_or_start(
    replay: &RwLock<ReplayBuffer>,
    dir: &SnapshotPath,
    identity: &str,
    policy: OnBadSnapshot,
    metrics: &CoreMetrics,
) -> Result<(SnapshotWriter, Option<RestoreReport>), SnapshotError> {
    let mut buffer = replay.write().expect("replay lock");
    let layout = *buffer.layout();
    let fresh = || SnapshotWriter::new(dir, identity, layout);
    let error = match snapshot::restore(dir, identity, &mut buffer) {
        Ok(Some((report, writer))) => return Ok((writer, Some(report))),
        Ok(None) => return Ok((fresh()?, None)),
        Err(error) => error,
    };
    metrics.record_snapshot_failure();
    if policy == OnBadSnapshot::Refuse {
        return Err(error);
    }
    match snapshot::set_aside(dir) {
        Ok(aside) => warn!(%error, moved_to = %aside.display(), "a snapshot that cannot be restored was set aside; the session starts empty"),
        Err(move_error) => warn!(%error, %move_error, "a snapshot that cannot be restored could not be set aside either"),
    }
    Ok((fresh()?, None))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fake::{self, FakeSimulators, FAKE_ENV};
    use crate::manager::{BufferRequest, Limits, SessionExtras};
    use crate::principal::Principal;

    /// A pass that took a session before it closed finds it closed and writes nothing: a session
    /// created again under the name may be restoring from that directory by then.
    #[tokio::test]
    async fn a_pass_that_took_a_closed_session_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let limits = Limits { memory_bytes: 64 << 20, session_idle_timeout_s: 0, ..Limits::default() };
        let config = ReplayConfig { snapshot_dir: Some(dir.path().to_path_buf()), ..ReplayConfig::default() };
        let manager = SessionManager::new(FakeSimulators::new(1), limits).with_snapshots(config);
        let extras = SessionExtras { buffer: Some(BufferRequest::Replay { capacity: 100 }), observation_view: None, name: Some("late".into()) };
        let local = Principal::local();
        let info = manager.create_session(&local, FAKE_ENV, 2, 0, &fake::fake_options(1), &extras).await.unwrap();
        manager.get(&local, &info.session_id).unwrap().lock().await.reset(None).await.unwrap();
        let stale = {
            let registry = manager.sessions.lock().unwrap();
            Snapshotted::of(&info.session_id, &registry.sessions[&info.session_id]).unwrap()
        };
        manager.close_session(&local, &info.session_id).await.unwrap();
        let manifest = dir.path().join(owner_dir("local")).join("late").join("MANIFEST");
        let written = std::fs::read(&manifest).expect("the last snapshot at close");
        // Something recorded after the last snapshot (as if the pass had been slower than the close).
        stale.replay.write().unwrap().record_first_frame(0, &[7; fake::FRAME_BYTES], 99);
        stale.write(&manager.metrics, &mut Throttle::new(0, None));
        assert_eq!(std::fs::read(&manifest).unwrap(), written, "nothing written after the session closed");
    }
}
