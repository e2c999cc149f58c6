//! The server's sessions: creation under explicit limits, lookup, close, and the environment catalog.

use std::collections::HashMap;
use std::hash::{BuildHasher, Hasher};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex as StdMutex, RwLock};
use std::time::Instant;

use radserve_replay::ReplayBuffer;
use tokio::sync::OnceCell;
use tracing::info;

use crate::budget::{self, MemoryBudget, Reservation};
use crate::catalog::{self, EnvNames, Options, FRAME_STACK};
use crate::error::CoreError;
use crate::metrics::CoreMetrics;
use crate::principal::{log_id, Principal};
use crate::session::{AutoresetMode, Session, SessionStats};
use crate::simulators::Simulators;

mod actor;
mod admission;
mod lease;
mod replay;
pub(crate) mod snapshots;
mod types;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod snapshot_tests;

pub use crate::actor::{ActingConfig, ActingRequest, ActingState, ActingStatus, LoadedPolicy, DEFAULT_POLICY_MEMORY_BYTES, RECENT_EPISODES};
pub use admission::MAX_STEP_OBSERVATION_BYTES;
pub use lease::{LeaseHold, Progress};
pub use snapshots::{OnBadSnapshot, ReplayConfig, MAX_NAME_BYTES};
pub use types::{
    BufferRequest, CatalogEntry, Limits, ReplayInfo, ReplaySource, SessionExtras, SessionInfo, SessionSummary, SharedSession,
    SnapshotInfo,
};

use lease::{elapsed_ms, Lease};
use replay::replay_info;
use snapshots::{SnapshotSlot, Snapshots};

struct Entry {
    session: SharedSession,
    /// The principal that created it: only it and admins may use it.
    owner: Arc<str>,
    /// The session's share of the memory budget, returned when the entry goes.
    memory: Vec<Reservation>,
    /// What Describe answers, without waiting for the session's lock (a step may hold it for as
    /// long as a worker takes): the parts fixed at creation, the live counters, the replay buffer.
    info: SessionInfo,
    stats: Arc<SessionStats>,
    replay: Option<Arc<RwLock<ReplayBuffer>>>,
    lease: Arc<Lease>,
    created: Instant,
    /// The name it was created with (unique per owner while it lives).
    name: Option<String>,
    /// Its replay's snapshot, for a named session with a replay buffer on a server that snapshots.
    snapshot: Option<Arc<SnapshotSlot>>,
    /// Its server-side policies and actor.
    actor: Arc<crate::actor::ActorSlot>,
}

pub struct SessionManager {
    simulators: Arc<dyn Simulators>,
    limits: Limits,
    budget: Arc<MemoryBudget>,
    names: OnceCell<EnvNames>,
    catalog: OnceCell<Vec<CatalogEntry>>,
    sessions: StdMutex<Registry>,
    next_id: AtomicU64,
    id_salt: std::collections::hash_map::RandomState,
    /// The time base of leases.
    clock: Instant,
    /// What every session has done since the server started (for the metrics endpoint).
    metrics: Arc<CoreMetrics>,
    /// Where and how named sessions' replay is snapshotted (None: it is not).
    snapshots: Option<Snapshots>,
    /// How server-side policies are loaded and run.
    acting: ActingConfig,
    /// ONNX Runtime's library, located at the first SetPolicy (or why it was not found).
    onnxruntime: tokio::sync::OnceCell<Result<std::path::PathBuf, String>>,
}

#[derive(Default)]
struct Registry {
    sessions: HashMap<String, Entry>,
    /// Environments of live sessions plus those being created.
    reserved_envs: usize,
    reserved_sessions: usize,
    reserved_replay_bytes: u64,
    /// (owner, name) of every named session, live or being created.
    names: std::collections::HashSet<(Arc<str>, String)>,
    /// The same counts per principal, and each principal's memory quota.
    principals: HashMap<Arc<str>, Usage>,
    closing: bool,
}

/// One principal's share of the server.
#[derive(Default)]
struct Usage {
    sessions: usize,
    envs: usize,
    /// Its memory quota, made when it first reserves memory (None: it has none).
    quota: Option<Arc<MemoryBudget>>,
}

impl SessionManager {
    pub fn new(simulators: Arc<dyn Simulators>, limits: Limits) -> SessionManager {
        let budget_bytes =
            if limits.memory_bytes > 0 { limits.memory_bytes } else { budget::default_budget_bytes(simulators.processes()) };
        info!(
            budget = %budget::human(budget_bytes),
            memory = %budget::human(budget::available_memory_bytes()),
            "memory budget (limits.memory_bytes)"
        );
        SessionManager {
            simulators,
            limits,
            budget: MemoryBudget::new(budget_bytes),
            names: OnceCell::new(),
            catalog: OnceCell::new(),
            sessions: StdMutex::new(Registry::default()),
            next_id: AtomicU64::new(1),
            id_salt: std::collections::hash_map::RandomState::new(),
            clock: Instant::now(),
            metrics: Arc::default(),
            snapshots: None,
            acting: ActingConfig::default(),
            onnxruntime: tokio::sync::OnceCell::new(),
        }
    }

    /// Counters and the step-latency histogram of every session since the server started.
    pub fn metrics(&self) -> &Arc<CoreMetrics> {
        &self.metrics
    }

    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Every id the simulators can host (asked once).
    pub async fn names(&self) -> Result<&EnvNames, CoreError> {
        self.names.get_or_try_init(|| async { Ok(self.simulators.env_names().await?) }).await
    }

    /// Every id with its default options and spaces. Building each environment once takes seconds, so
    /// this is computed once and kept.
    pub async fn catalog(&self) -> Result<&[CatalogEntry], CoreError> {
        let entries = self
            .catalog
            .get_or_try_init(|| async {
                let ids = self.names().await?.all_ids();
                let defaults: Vec<Options> = ids.iter().map(catalog::default_options).collect();
                let requests = ids
                    .iter()
                    .zip(&defaults)
                    .map(|(id, options)| {
                        let mut worker_options = options.clone();
                        worker_options.remove(FRAME_STACK);
                        (id.clone(), worker_options)
                    })
                    .collect();
                let specs = self.simulators.env_specs(requests).await?;
                Ok::<_, CoreError>(
                    ids.into_iter()
                        .zip(defaults)
                        .zip(specs)
                        .map(|((id, default_options), spec)| {
                            let frame_stack = default_options[FRAME_STACK].as_int().unwrap_or(1) as usize;
                            let spaces = spec.map(|spec| (spec.observation.stacked(frame_stack), spec.action));
                            CatalogEntry { id, default_options, spaces }
                        })
                        .collect(),
                )
            })
            .await?;
        Ok(entries)
    }

    /// The simulator processes stuck in a call for longer than `after` (see `Simulators::overdue`).
    pub fn overdue_simulators(&self, after: std::time::Duration) -> Vec<usize> {
        self.simulators.overdue(after)
    }

    fn new_session_id(&self) -> String {
        let counter = self.next_id.fetch_add(1, Ordering::Relaxed);
        let mut hasher = self.id_salt.build_hasher();
        hasher.write_u64(counter);
        format!("s{counter}-{:016x}", hasher.finish())
    }

    /// The session, its lease renewed: every call on a session goes through here.
    pub fn get(&self, caller: &Principal, session_id: &str) -> Result<SharedSession, CoreError> {
        let registry = self.sessions.lock().expect("registry lock");
        Ok(self.touch(&registry, caller, session_id)?.session.clone())
    }

    /// The entry of `session_id` if `caller` may use it, its lease renewed. A session of another
    /// principal is unknown to the caller: the answer does not confirm that it exists.
    fn touch<'a>(&self, registry: &'a Registry, caller: &Principal, session_id: &str) -> Result<&'a Entry, CoreError> {
        self.touch_if(registry, session_id, |owner| caller.may_use(owner))
    }

    fn touch_if<'a>(&self, registry: &'a Registry, session_id: &str, allowed: impl Fn(&str) -> bool) -> Result<&'a Entry, CoreError> {
        let entry = registry
            .sessions
            .get(session_id)
            .filter(|entry| allowed(&entry.owner))
            .ok_or_else(|| CoreError::UnknownSession(session_id.to_string()))?;
        entry.lease.last_used_ms.store(elapsed_ms(self.clock), Ordering::Relaxed);
        Ok(entry)
    }

    /// Every open session `caller` may see (an admin or a monitor: all of them), oldest first.
    pub fn list_sessions(&self, caller: &Principal) -> Vec<SessionSummary> {
        let registry = self.sessions.lock().expect("registry lock");
        // One clock reading for every age: read per entry, a later entry's reading could make a younger
        // session look older than one created microseconds before it (and flip the order below).
        let now = Instant::now();
        let mut sessions: Vec<SessionSummary> = registry
            .sessions
            .iter()
            .filter(|(_, entry)| caller.may_see(&entry.owner))
            .map(|(id, entry)| SessionSummary {
                session_id: id.clone(),
                name: entry.name.clone(),
                owner: entry.owner.to_string(),
                env_id: entry.info.env_id.clone(),
                num_envs: entry.info.num_envs,
                memory_bytes: entry.memory.iter().map(Reservation::bytes).sum(),
                idle: self.idle(entry),
                open_streams: entry.lease.holds.load(Ordering::Acquire),
                age: now.saturating_duration_since(entry.created),
                replay_transitions: entry.replay.as_ref().map_or(0, |replay| replay.read().expect("replay lock").len() as u64),
                replay_bytes: entry.replay.as_ref().map_or(0, |replay| replay.read().expect("replay lock").layout().memory_bytes() as u64),
                snapshot: entry.snapshot.as_ref().zip(entry.replay.as_ref()).map(|(snapshot, replay)| snapshot.info(replay)),
            })
            .collect();
        sessions.sort_by(|a, b| b.age.cmp(&a.age).then_with(|| a.session_id.cmp(&b.session_id)));
        sessions
    }

    /// Never waits for the session's lock: a step in progress (or a stuck worker) does not delay it.
    pub async fn describe(&self, caller: &Principal, session_id: &str) -> Result<SessionInfo, CoreError> {
        let (mut info, stats, replay, snapshot, actor) = {
            let registry = self.sessions.lock().expect("registry lock");
            let entry = self.touch_if(&registry, session_id, |owner| caller.may_see(owner))?;
            (entry.info.clone(), entry.stats.clone(), entry.replay.clone(), entry.snapshot.clone(), entry.actor.clone())
        };
        let acting = actor.status();
        info.acting = (acting.state != ActingState::Idle || acting.policy_version.is_some()).then_some(acting);
        info.seed = stats.seed.load(Ordering::Relaxed);
        info.total_env_steps = stats.total_env_steps.load(Ordering::Relaxed);
        info.episodes_completed = stats.episodes_completed.load(Ordering::Relaxed);
        info.replay = replay.as_ref().map(|replay| replay_info(&replay.read().expect("replay lock")));
        if let (Some(replay_info), Some(snapshot), Some(replay)) = (info.replay.as_mut(), snapshot, replay) {
            replay_info.snapshot = Some(snapshot.info(&replay));
        }
        Ok(info)
    }

    /// Closes a session of `caller` (an admin: any session); a named session's replay gets its last
    /// snapshot.
    pub async fn close_session(&self, caller: &Principal, session_id: &str) -> Result<(), CoreError> {
        self.close_session_with(caller, session_id, false).await
    }

    /// The same, removing the named session's snapshot instead when `discard_snapshot`.
    pub async fn close_session_with(&self, caller: &Principal, session_id: &str, discard_snapshot: bool) -> Result<(), CoreError> {
        let entry = {
            let mut registry = self.sessions.lock().expect("registry lock");
            match registry.sessions.get(session_id) {
                Some(entry) if caller.may_use(&entry.owner) => registry.sessions.remove(session_id).expect("present"),
                _ => return Err(CoreError::UnknownSession(session_id.to_string())),
            }
        };
        let reason = if *entry.owner == *caller.name() {
            "its owner closed it".to_string()
        } else {
            format!("admin '{}' closed it", caller.name())
        };
        self.close_entry(session_id, entry, &reason, discard_snapshot).await;
        Ok(())
    }

    /// Closes a session already taken out of the registry; its memory returns with the entry.
    async fn close_entry(&self, session_id: &str, entry: Entry, reason: &str, discard_snapshot: bool) {
        entry.lease.closed.send_replace(true);
        entry.actor.stop().await;
        let mut session = entry.session.lock().await;
        session.close().await;
        // Nothing records any more: the last snapshot holds everything. The name is free only after
        // it, so a session created again under it restores all of it.
        self.final_snapshot(session_id, &entry, discard_snapshot).await;
        if let Some(name) = &entry.name {
            self.sessions.lock().expect("registry lock").names.remove(&(entry.owner.clone(), name.clone()));
        }
        self.release(&entry.owner, session.num_envs(), 1);
        self.release_replay(&session);
        info!(session = log_id(session_id), owner = %entry.owner, env = %entry.info.env_id, reason, "session closed");
    }

    /// From now on, CreateSession is refused with UNAVAILABLE (the server is shutting down); open
    /// sessions keep working until `shutdown`.
    pub fn refuse_new_sessions(&self) {
        self.sessions.lock().expect("registry lock").closing = true;
    }

    /// Refuses new sessions and closes every open one.
    pub async fn shutdown(&self) {
        let entries: Vec<(String, Entry)> = {
            let mut registry = self.sessions.lock().expect("registry lock");
            registry.closing = true;
            registry.sessions.drain().collect()
        };
        self.hurry_snapshots();
        for (id, entry) in entries {
            self.close_entry(&id, entry, "the server is shutting down", false).await;
        }
    }
}

pub fn describe(session_id: &str, session: &Session) -> SessionInfo {
    SessionInfo {
        session_id: session_id.to_string(),
        name: None,
        env_id: session.config.env.full(),
        num_envs: session.num_envs(),
        seed: session.config.seed,
        options: session.config.options.clone(),
        observation_space: session.observation_space.clone(),
        action_space: session.frame_spec.action.clone(),
        frame_stack: session.config.frame_stack,
        autoreset_mode: AutoresetMode::SameStep,
        total_env_steps: session.total_env_steps(),
        episodes_completed: session.episodes_completed(),
        replay: session.replay().map(|replay| replay_info(&replay.read().expect("replay lock"))),
        acting: None,
    }
}
