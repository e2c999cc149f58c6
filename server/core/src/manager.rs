//! The server's sessions: creation under explicit limits, lookup, close, and the environment catalog.

use std::collections::HashMap;
use std::hash::{BuildHasher, Hasher};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex as StdMutex, RwLock};
use std::time::{Duration, Instant};

use radserve_replay::{BufferKind, ObservationFormat, ProducerPermit, ReplayBuffer, ReplayLayout};

use serde::{Deserialize, Serialize};
use tokio::sync::{watch, Mutex, OnceCell};
use tracing::info;

use crate::bounds;
use crate::budget::{self, MemoryBudget, Reservation};
use crate::catalog::{self, EnvId, EnvNames, OptionValue, Options, FRAME_STACK};
use crate::error::CoreError;
use crate::metrics::CoreMetrics;
use crate::principal::{log_id, Principal};
use crate::session::{check_seed, AutoresetMode, Session, SessionConfig, SessionStats};
use crate::simulators::Simulators;
use crate::space::{DType, Space};

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    /// Sessions open at once on the server (every principal's together).
    pub max_sessions: usize,
    /// Environments in one session (`num_envs`).
    pub max_envs_per_session: usize,
    /// Environments across all sessions of the server.
    pub max_total_envs: usize,
    /// Bytes all sessions' replay buffers may take together (computed up front at creation).
    pub replay_memory_bytes: u64,
    /// SampleBatches streams open at once on one session (each has a sampler thread).
    pub max_streams_per_session: usize,
    /// Bytes of batches one sample stream may hold at once: (prefetch + 2) batches of observations.
    pub stream_memory_bytes: u64,
    /// Seconds a session may go without a call on it and without an open stream before the server
    /// closes it (a learner that crashed leaves its sessions behind); 0 keeps sessions until closed.
    pub session_idle_timeout_s: u64,
    /// Bytes every session, buffer and stream of the server may take together, reserved before each
    /// is allocated (envs at their measured cost per family, frames, replay, stream batches). 0: three
    /// quarters of the host's (or the container's) memory, less 512 MiB per worker.
    pub memory_bytes: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_sessions: 64,
            max_envs_per_session: 256,
            max_total_envs: 1024,
            replay_memory_bytes: 8 << 30,
            max_streams_per_session: 4,
            stream_memory_bytes: 4 << 30,
            session_idle_timeout_s: 300,
            memory_bytes: 0,
        }
    }
}

/// What a session may have besides its environments.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct SessionExtras {
    /// A replay or rollout buffer recording every step.
    pub buffer: Option<BufferRequest>,
    /// Return observations through this evaluation view (`center_crop(84)`, `center_translate(108)`).
    pub observation_view: Option<String>,
}

/// The buffer a session is created with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BufferRequest {
    /// Uniform replay over the last `capacity` transitions.
    Replay { capacity: usize },
    /// The last `steps` steps of every env, for on-policy learners.
    Rollout { steps: usize },
}

/// A session's replay buffer, as a client sees it.
#[derive(Clone, Debug, PartialEq)]
pub struct ReplayInfo {
    pub capacity: usize,
    /// Transitions that can be sampled now.
    pub size: usize,
    pub inserts: u64,
    pub samples: u64,
    /// Minibatches sampled since creation.
    pub batches: u64,
    /// Minibatches sampled per second, over the last 5 seconds.
    pub batches_per_second: f64,
    pub memory_bytes: u64,
    pub frames_per_transition: f64,
    /// SampleBatches streams producing from it now.
    pub active_streams: usize,
    /// For a rollout buffer: the steps per env it keeps.
    pub rollout_steps: Option<usize>,
}

/// What a sampler needs of a session: its buffer, what its observations and actions are, and the
/// stream's place among the session's streams (reserved; dropping it frees the place).
pub struct ReplaySource {
    pub buffer: Arc<RwLock<ReplayBuffer>>,
    pub format: ObservationFormat,
    pub action_space: Space,
    pub permit: ProducerPermit,
}

/// A catalog entry: an id with its default options and the spaces they give.
#[derive(Clone, Debug)]
pub struct CatalogEntry {
    pub id: EnvId,
    pub default_options: Options,
    /// (stacked observation space, action space), or why the simulator could not build the env.
    pub spaces: Result<(Space, Space), String>,
}

/// What a client learns about a session.
#[derive(Clone, Debug)]
pub struct SessionInfo {
    pub session_id: String,
    pub env_id: String,
    pub num_envs: usize,
    pub seed: u64,
    pub options: Options,
    pub observation_space: Space,
    pub action_space: Space,
    pub frame_stack: usize,
    pub autoreset_mode: AutoresetMode,
    pub total_env_steps: u64,
    pub episodes_completed: u64,
    pub replay: Option<ReplayInfo>,
}

pub type SharedSession = Arc<Mutex<Session>>;

/// When a session was last used, and what keeps it in use now: any call on it renews the lease, an
/// open stream or acting channel holds it.
#[derive(Debug)]
pub struct Lease {
    /// Milliseconds after the manager's start.
    last_used_ms: AtomicU64,
    holds: AtomicUsize,
    /// Turns true when the session is closed, for what holds the lease (streams, acting channels).
    closed: watch::Sender<bool>,
}

impl Lease {
    fn new(now_ms: u64) -> Lease {
        Lease { last_used_ms: AtomicU64::new(now_ms), holds: AtomicUsize::new(0), closed: watch::Sender::new(false) }
    }
}

/// A stream's hold on its session's lease: the session is not reaped while one exists.
#[derive(Debug)]
pub struct LeaseHold {
    lease: Arc<Lease>,
    clock: Instant,
}

impl LeaseHold {
    /// Resolves once the session is closed (by its client, its lease or shutdown): what holds it
    /// should end and free what it has.
    /// The future owns its subscription: a long-lived holder makes it once and polls it again and
    /// again (an acting channel, between requests).
    pub fn session_closed(&self) -> impl std::future::Future<Output = ()> + Send + 'static {
        let mut closed = self.lease.closed.subscribe();
        async move {
            // An error means the lease is gone, which only happens once the session is.
            let _ = closed.wait_for(|closed| *closed).await;
        }
    }
}

impl Drop for LeaseHold {
    fn drop(&mut self) {
        self.lease.last_used_ms.store(elapsed_ms(self.clock), Ordering::Relaxed);
        self.lease.holds.fetch_sub(1, Ordering::AcqRel);
    }
}

fn elapsed_ms(clock: Instant) -> u64 {
    clock.elapsed().as_millis() as u64
}

/// One open session as an operator sees it (ListSessions).
#[derive(Clone, Debug, PartialEq)]
pub struct SessionSummary {
    pub session_id: String,
    /// The principal that created it.
    pub owner: String,
    pub env_id: String,
    pub num_envs: usize,
    pub memory_bytes: u64,
    pub idle: Duration,
    pub open_streams: usize,
    pub age: Duration,
    /// Transitions its replay buffer holds now, and the bytes the buffer takes (0 without one).
    pub replay_transitions: u64,
    pub replay_bytes: u64,
}

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
}

#[derive(Default)]
struct Registry {
    sessions: HashMap<String, Entry>,
    /// Environments of live sessions plus those being created.
    reserved_envs: usize,
    reserved_sessions: usize,
    reserved_replay_bytes: u64,
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

    pub async fn create_session(
        &self,
        caller: &Principal,
        env_id: &str,
        num_envs: usize,
        seed: u64,
        overrides: &Options,
        extras: &SessionExtras,
    ) -> Result<SessionInfo, CoreError> {
        if num_envs == 0 {
            return Err(CoreError::InvalidSession("num_envs must be at least 1".into()));
        }
        if num_envs > self.limits.max_envs_per_session {
            return Err(CoreError::OverLimit(format!(
                "num_envs {num_envs} exceeds this server's limit of {} environments per session",
                self.limits.max_envs_per_session
            )));
        }
        check_seed(seed, num_envs)?;
        bounds::check_len("env_id", env_id, bounds::MAX_ID_BYTES)?;
        if let Some(view) = &extras.observation_view {
            bounds::check_len("observation_view", view, radserve_augment::MAX_PIPELINE_TEXT_BYTES)?;
        }
        if let Some(buffer) = extras.buffer {
            self.precheck_buffer(buffer, num_envs)?;
        }
        let env = self.names().await?.parse(env_id)?;
        let options = catalog::resolve_options(&env, overrides)?;
        let frame_stack = options[FRAME_STACK].as_int().unwrap_or(1) as usize;
        check_batch_size(&options, num_envs, extras)?;

        // Before anything is built: the envs' own memory at their family's measured cost.
        let per_env = budget::env_cost_bytes(&env, &options);
        let quota = self.quota(caller);
        let envs_memory = self.budget.try_reserve_within(
            quota.as_ref(),
            per_env.saturating_mul(num_envs as u64),
            &format!("{num_envs} envs of {} (~{} each)", env.full(), budget::human(per_env)),
        )?;
        self.reserve(caller, num_envs)?;
        let owner = caller.shared_name();
        let config = SessionConfig { env, num_envs, seed, options, frame_stack };
        let mut session = match Session::create(self.simulators.as_ref(), config).await {
            Ok(session) => session.with_metrics(self.metrics.clone()),
            Err(error) => {
                self.release(&owner, num_envs, 1);
                return Err(error);
            }
        };
        let prepared = match &extras.observation_view {
            Some(view) => session.set_view(view),
            None => Ok(()),
        };
        let prepared = prepared.and_then(|()| check_observation_bytes(&session));
        let prepared = prepared.and_then(|()| {
            let frames = self.budget.try_reserve_within(
                quota.as_ref(),
                frame_buffer_bytes(&session),
                &format!("the frame buffers of {num_envs} envs"),
            )?;
            let replay = match extras.buffer {
                Some(buffer) => Some(self.attach_replay(&mut session, buffer, quota.as_ref())?),
                None => None,
            };
            Ok([Some(envs_memory), Some(frames), replay].into_iter().flatten().collect::<Vec<_>>())
        });
        let memory = match prepared {
            Ok(memory) => memory,
            Err(error) => {
                session.close().await;
                self.release(&owner, num_envs, 1);
                return Err(error);
            }
        };
        let session_id = self.new_session_id();
        let info = describe(&session_id, &session);
        let (stats, replay) = (session.stats.clone(), session.replay().cloned());
        let shared = Arc::new(Mutex::new(session));
        let rejected = {
            let mut registry = self.sessions.lock().expect("registry lock");
            if registry.closing {
                true
            } else {
                let lease = Lease::new(elapsed_ms(self.clock));
                let entry = Entry {
                    session: shared.clone(),
                    owner: owner.clone(),
                    memory,
                    info: info.clone(),
                    stats,
                    replay,
                    lease: Arc::new(lease),
                    created: Instant::now(),
                };
                registry.sessions.insert(session_id.clone(), entry);
                false
            }
        };
        if rejected {
            let mut session = shared.lock().await;
            session.close().await;
            self.release(&owner, num_envs, 1);
            self.release_replay(&session);
            return Err(CoreError::ShuttingDown);
        }
        info!(session = log_id(&session_id), owner = %owner, env = %info.env_id, envs = num_envs, seed, "session created");
        Ok(info)
    }

    /// The memory quota of `caller`, if it has one (made on first use, then shared by its sessions).
    fn quota(&self, caller: &Principal) -> Option<Arc<MemoryBudget>> {
        let limit = caller.limits().memory_bytes?;
        let mut registry = self.sessions.lock().expect("registry lock");
        let usage = registry.principals.entry(caller.shared_name()).or_default();
        Some(usage.quota.get_or_insert_with(|| MemoryBudget::quota(limit, caller.shared_name())).clone())
    }

    fn reserve(&self, caller: &Principal, num_envs: usize) -> Result<(), CoreError> {
        let mut registry = self.sessions.lock().expect("registry lock");
        if registry.closing {
            return Err(CoreError::ShuttingDown);
        }
        let name = caller.shared_name();
        let (sessions, envs) = registry.principals.get(&name).map_or((0, 0), |usage| (usage.sessions, usage.envs));
        if let Some(max) = caller.limits().max_sessions.filter(|&max| sessions >= max) {
            return Err(CoreError::OverLimit(format!(
                "principal '{name}' already has {sessions} sessions open, its limit of {max} (max_sessions in its \
                 tokens file entry); close one first"
            )));
        }
        if let Some(max) = caller.limits().max_envs.filter(|&max| envs + num_envs > max) {
            return Err(CoreError::OverLimit(format!(
                "{num_envs} more environments would give principal '{name}' {}, above its limit of {max} (max_envs \
                 in its tokens file entry)",
                envs + num_envs
            )));
        }
        if registry.reserved_sessions >= self.limits.max_sessions {
            return Err(CoreError::OverLimit(format!(
                "this server already hosts {} sessions, its limit; close one first",
                registry.reserved_sessions
            )));
        }
        if registry.reserved_envs + num_envs > self.limits.max_total_envs {
            return Err(CoreError::OverLimit(format!(
                "{num_envs} more environments would make {} on this server, above its limit of {}",
                registry.reserved_envs + num_envs,
                self.limits.max_total_envs
            )));
        }
        registry.reserved_envs += num_envs;
        registry.reserved_sessions += 1;
        let usage = registry.principals.entry(name).or_default();
        usage.envs += num_envs;
        usage.sessions += 1;
        Ok(())
    }

    /// What can be known of a buffer before any environment is built (its frame size comes from the
    /// simulator): a capacity in range, and at least the bookkeeping bytes of every transition within
    /// the replay budget. The exact size is checked again once the frames are known.
    fn precheck_buffer(&self, buffer: BufferRequest, num_envs: usize) -> Result<(), CoreError> {
        let capacity = match buffer {
            BufferRequest::Replay { capacity } => capacity,
            BufferRequest::Rollout { steps } => steps.saturating_mul(num_envs),
        };
        radserve_replay::check_capacity(capacity)?;
        let least = (capacity as u64).saturating_mul(radserve_replay::MIN_BYTES_PER_TRANSITION as u64);
        let budget = self.limits.replay_memory_bytes;
        if least > budget {
            return Err(CoreError::OverLimit(format!(
                "a replay buffer of {capacity} transitions takes at least {:.2} GiB ({} bytes per transition \
                 before its frames), above this server's replay budget of {:.2} GiB (limits.replay_memory_bytes)",
                gib(least),
                radserve_replay::MIN_BYTES_PER_TRANSITION,
                gib(budget)
            )));
        }
        Ok(())
    }

    /// Reserve memory for `what` against the server's budget (a stream's batches, an acting
    /// channel); held until the reservation is dropped.
    pub fn reserve_memory(&self, caller: &Principal, bytes: u64, what: &str) -> Result<Reservation, CoreError> {
        self.budget.try_reserve_within(self.quota(caller).as_ref(), bytes, what)
    }

    /// Reserve the batches a sample stream holds at once, `bytes` for (`prefetch` + 2) batches: within
    /// the per-stream limit and the memory budget, for as long as the reservation lives.
    pub fn reserve_stream(&self, caller: &Principal, bytes: u64, prefetch: usize) -> Result<Reservation, CoreError> {
        let limit = self.limits.stream_memory_bytes;
        if bytes > limit {
            return Err(CoreError::OverLimit(format!(
                "this stream would hold {bytes} bytes of batches ((prefetch {prefetch} + 2) batches of observations), over \
                 this server's limit of {limit} (limits.stream_memory_bytes): lower prefetch or batch_size"
            )));
        }
        self.budget.try_reserve_within(
            self.quota(caller).as_ref(),
            bytes,
            &format!("a sample stream of (prefetch {prefetch} + 2) batches"),
        )
    }

    /// The server's memory budget: (bytes reserved now, limit).
    pub fn memory(&self) -> (u64, u64) {
        (self.budget.used(), self.budget.limit())
    }

    /// Give `session` a replay (or rollout) buffer if the server's budget allows it.
    fn attach_replay(
        &self,
        session: &mut Session,
        buffer: BufferRequest,
        quota: Option<&Arc<MemoryBudget>>,
    ) -> Result<Reservation, CoreError> {
        let frame = &session.frame_spec.observation;
        if !matches!(frame.dtype(), DType::Uint8 | DType::Float32) {
            return Err(CoreError::InvalidSession(format!(
                "replay keeps uint8 images or float32 vectors; {} observes {}",
                session.config.env.full(),
                frame.describe()
            )));
        }
        let (num_envs, frame_stack) = (session.num_envs(), session.config.frame_stack);
        let (frame_bytes, action_bytes) = (frame.num_bytes(), session.frame_spec.action.num_bytes());
        let layout = match buffer {
            BufferRequest::Replay { capacity } => {
                ReplayLayout { kind: BufferKind::Replay, capacity, num_envs, frame_stack, frame_bytes, action_bytes }
            }
            BufferRequest::Rollout { steps } => ReplayLayout::rollout(steps, num_envs, frame_stack, frame_bytes, action_bytes),
        };
        let capacity = layout.capacity;
        layout.validate()?;
        let bytes = layout.memory_bytes() as u64;
        {
            let mut registry = self.sessions.lock().expect("registry lock");
            let budget = self.limits.replay_memory_bytes;
            if registry.reserved_replay_bytes.saturating_add(bytes) > budget {
                return Err(CoreError::OverLimit(format!(
                    "a replay buffer of {capacity} transitions for {} envs of {} takes {:.2} GiB ({} bytes per frame, \
                     {:.3} frames per transition); with the {:.2} GiB already reserved it would exceed this server's \
                     replay budget of {:.2} GiB (limits.replay_memory_bytes)",
                    layout.num_envs,
                    session.config.env.full(),
                    gib(bytes),
                    layout.frame_bytes,
                    layout.frames_per_transition(),
                    gib(registry.reserved_replay_bytes),
                    gib(budget)
                )));
            }
            registry.reserved_replay_bytes += bytes;
        }
        let what = format!("a replay buffer of {capacity} transitions");
        let reservation = match self.budget.try_reserve_within(quota, bytes, &what) {
            Ok(reservation) => reservation,
            Err(error) => {
                self.sessions.lock().expect("registry lock").reserved_replay_bytes -= bytes;
                return Err(error);
            }
        };
        match ReplayBuffer::new(layout) {
            Ok(buffer) => {
                session.attach_replay(Arc::new(RwLock::new(buffer)));
                Ok(reservation)
            }
            Err(error) => {
                self.sessions.lock().expect("registry lock").reserved_replay_bytes -= bytes;
                Err(error.into())
            }
        }
    }

    fn release_replay(&self, session: &Session) {
        if let Some(replay) = session.replay() {
            let bytes = replay.read().expect("replay lock").layout().memory_bytes() as u64;
            self.sessions.lock().expect("registry lock").reserved_replay_bytes -= bytes;
        }
    }

    /// The replay buffer of a session, with what a sampler needs to know about it.
    pub async fn replay_source(&self, caller: &Principal, session_id: &str) -> Result<ReplaySource, CoreError> {
        let session = self.get(caller, session_id)?;
        let session = session.lock().await;
        let Some(buffer) = session.replay() else {
            return Err(CoreError::NoReplayBuffer(session_id.to_string()));
        };
        // Reserved here, atomically: concurrent requests cannot all pass a check made before any
        // of them is counted.
        let max = self.limits.max_streams_per_session;
        let Some(permit) = buffer.read().expect("replay lock").admit_producer(max) else {
            return Err(CoreError::OverLimit(format!(
                "session {session_id} already has {max} sample streams open, this server's limit \
                 (limits.max_streams_per_session); close one first"
            )));
        };
        let frame = &session.frame_spec.observation;
        let format = match (frame.dtype(), frame.shape()) {
            (DType::Uint8, &[channels, height, width]) => {
                ObservationFormat::Image(radserve_augment::FrameShape::new(session.config.frame_stack, channels, height, width))
            }
            _ => ObservationFormat::State(session.config.frame_stack * frame.num_elements()),
        };
        Ok(ReplaySource { buffer: buffer.clone(), format, action_space: session.frame_spec.action.clone(), permit })
    }

    fn release(&self, owner: &Arc<str>, num_envs: usize, sessions: usize) {
        let mut registry = self.sessions.lock().expect("registry lock");
        registry.reserved_envs -= num_envs;
        registry.reserved_sessions -= sessions;
        if let Some(usage) = registry.principals.get_mut(owner) {
            usage.envs -= num_envs;
            usage.sessions -= sessions;
        }
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

    /// How long nothing has used the session: zero while a stream holds it.
    fn idle(&self, entry: &Entry) -> Duration {
        if entry.lease.holds.load(Ordering::Acquire) > 0 {
            return Duration::ZERO;
        }
        Duration::from_millis(elapsed_ms(self.clock).saturating_sub(entry.lease.last_used_ms.load(Ordering::Relaxed)))
    }

    /// Keep the session's lease alive for as long as the returned hold lives (a stream on it).
    pub fn hold(&self, caller: &Principal, session_id: &str) -> Result<LeaseHold, CoreError> {
        let registry = self.sessions.lock().expect("registry lock");
        let entry = self.touch(&registry, caller, session_id)?;
        entry.lease.holds.fetch_add(1, Ordering::AcqRel);
        Ok(LeaseHold { lease: entry.lease.clone(), clock: self.clock })
    }

    /// Every open session `caller` may see (an admin or a monitor: all of them), oldest first.
    pub fn list_sessions(&self, caller: &Principal) -> Vec<SessionSummary> {
        let registry = self.sessions.lock().expect("registry lock");
        let mut sessions: Vec<SessionSummary> = registry
            .sessions
            .iter()
            .filter(|(_, entry)| caller.may_see(&entry.owner))
            .map(|(id, entry)| SessionSummary {
                session_id: id.clone(),
                owner: entry.owner.to_string(),
                env_id: entry.info.env_id.clone(),
                num_envs: entry.info.num_envs,
                memory_bytes: entry.memory.iter().map(Reservation::bytes).sum(),
                idle: self.idle(entry),
                open_streams: entry.lease.holds.load(Ordering::Acquire),
                age: entry.created.elapsed(),
                replay_transitions: entry.replay.as_ref().map_or(0, |replay| replay.read().expect("replay lock").len() as u64),
                replay_bytes: entry.replay.as_ref().map_or(0, |replay| replay.read().expect("replay lock").layout().memory_bytes() as u64),
            })
            .collect();
        sessions.sort_by(|a, b| b.age.cmp(&a.age).then_with(|| a.session_id.cmp(&b.session_id)));
        sessions
    }

    /// The idle time after which a session is reaped (None: never).
    pub fn idle_timeout(&self) -> Option<Duration> {
        (self.limits.session_idle_timeout_s > 0).then(|| Duration::from_secs(self.limits.session_idle_timeout_s))
    }

    /// Closes every session whose lease expired: no open stream, and no call for longer than the
    /// idle timeout. Returns the ids closed.
    pub async fn reap_idle(&self) -> Vec<String> {
        let Some(timeout) = self.idle_timeout() else { return Vec::new() };
        // Chosen and removed under one lock: a call cannot renew a lease between the two.
        let expired: Vec<(String, Entry, Duration)> = {
            let mut registry = self.sessions.lock().expect("registry lock");
            let ids: Vec<String> =
                registry.sessions.iter().filter(|(_, entry)| self.idle(entry) > timeout).map(|(id, _)| id.clone()).collect();
            ids.into_iter()
                .filter_map(|id| {
                    let entry = registry.sessions.remove(&id)?;
                    let idle = self.idle(&entry);
                    Some((id, entry, idle))
                })
                .collect()
        };
        let mut reaped = Vec::new();
        for (id, entry, idle) in expired {
            let reason = format!(
                "its lease expired: no call and no open stream for {} s (limits.session_idle_timeout_s = {})",
                idle.as_secs(),
                timeout.as_secs()
            );
            self.close_entry(&id, entry, &reason).await;
            reaped.push(id);
        }
        reaped
    }

    /// Reaps idle sessions until the manager is dropped or shut down, checking a few times per
    /// timeout.
    pub async fn run_reaper(self: Arc<Self>) {
        let Some(timeout) = self.idle_timeout() else { return };
        let period = (timeout / 4).clamp(Duration::from_millis(100), Duration::from_secs(10));
        loop {
            tokio::time::sleep(period).await;
            if self.sessions.lock().expect("registry lock").closing {
                return;
            }
            self.reap_idle().await;
        }
    }

    /// Never waits for the session's lock: a step in progress (or a stuck worker) does not delay it.
    pub async fn describe(&self, caller: &Principal, session_id: &str) -> Result<SessionInfo, CoreError> {
        let (mut info, stats, replay) = {
            let registry = self.sessions.lock().expect("registry lock");
            let entry = self.touch_if(&registry, session_id, |owner| caller.may_see(owner))?;
            (entry.info.clone(), entry.stats.clone(), entry.replay.clone())
        };
        info.seed = stats.seed.load(Ordering::Relaxed);
        info.total_env_steps = stats.total_env_steps.load(Ordering::Relaxed);
        info.episodes_completed = stats.episodes_completed.load(Ordering::Relaxed);
        info.replay = replay.map(|replay| replay_info(&replay.read().expect("replay lock")));
        Ok(info)
    }

    /// Closes a session of `caller` (an admin: any session).
    pub async fn close_session(&self, caller: &Principal, session_id: &str) -> Result<(), CoreError> {
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
        self.close_entry(session_id, entry, &reason).await;
        Ok(())
    }

    /// Closes a session already taken out of the registry; its memory returns with the entry.
    async fn close_entry(&self, session_id: &str, entry: Entry, reason: &str) {
        entry.lease.closed.send_replace(true);
        let mut session = entry.session.lock().await;
        session.close().await;
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
        for (id, entry) in entries {
            self.close_entry(&id, entry, "the server is shutting down").await;
        }
    }
}

pub fn describe(session_id: &str, session: &Session) -> SessionInfo {
    SessionInfo {
        session_id: session_id.to_string(),
        env_id: session.config.env.full(),
        num_envs: session.num_envs(),
        seed: session.config.seed,
        options: session.config.options.clone(),
        observation_space: session.observation_space.clone(),
        action_space: session.frame_spec.action.clone(),
        frame_stack: session.config.frame_stack,
        autoreset_mode: AutoresetMode::SameStep,
        total_env_steps: session.total_env_steps,
        episodes_completed: session.episodes_completed,
        replay: session.replay().map(|replay| replay_info(&replay.read().expect("replay lock"))),
    }
}

fn replay_info(replay: &ReplayBuffer) -> ReplayInfo {
    let layout = replay.layout();
    ReplayInfo {
        capacity: layout.capacity,
        size: replay.len(),
        inserts: replay.counters().inserts,
        samples: replay.counters().samples,
        batches: replay.counters().batches,
        batches_per_second: replay.batches_per_second(),
        memory_bytes: layout.memory_bytes() as u64,
        frames_per_transition: layout.frames_per_transition(),
        active_streams: replay.active_producers(),
        rollout_steps: match layout.kind {
            BufferKind::Rollout { steps } => Some(steps),
            BufferKind::Replay => None,
        },
    }
}

/// The most bytes of observations one step may return for all of a session's envs. A step's
/// response carries them and, when every episode ends at once, as many final observations; both
/// must fit in one gRPC message (the service's 256 MiB).
pub const MAX_STEP_OBSERVATION_BYTES: usize = 96 << 20;

/// The buffers a session allocates for its frames: the stacks, the frame and final frame per env in
/// the memory shared with workers, and a step's observations and final observations as returned.
fn frame_buffer_bytes(session: &Session) -> u64 {
    let frame = session.frame_spec.observation.num_bytes() as u64;
    let observation = session.observation_space.num_bytes() as u64;
    let per_env = frame * session.config.frame_stack as u64 + 2 * frame + 2 * observation;
    per_env.saturating_mul(session.num_envs() as u64)
}

/// Refuses a session whose step observations could not be sent in one response.
fn check_observation_bytes(session: &Session) -> Result<(), CoreError> {
    let per_env = session.observation_space.num_bytes();
    let total = per_env.saturating_mul(session.num_envs());
    if total > MAX_STEP_OBSERVATION_BYTES {
        return Err(CoreError::OverLimit(format!(
            "{} envs of {} observe {per_env} bytes each ({} as viewed), {total} bytes a step; the most a step \
             may return is {MAX_STEP_OBSERVATION_BYTES} bytes: use fewer envs, smaller frames or a smaller frame_stack",
            session.num_envs(),
            session.config.env.full(),
            session.observation_space.describe(),
        )));
    }
    Ok(())
}

fn gib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 30) as f64
}

/// Refuses a `batch_size` above `num_envs`, and a buffer for a session in EnvPool's asynchronous mode,
/// before anything is built.
fn check_batch_size(options: &Options, num_envs: usize, extras: &SessionExtras) -> Result<(), CoreError> {
    let batch = options.get(catalog::BATCH_SIZE).and_then(OptionValue::as_int).unwrap_or(0);
    if batch as usize > num_envs {
        return Err(CoreError::InvalidOption(format!(
            "option 'batch_size' is {batch}, above num_envs {num_envs}: a recv returns at most every env; give \
             batch_size in [1, {num_envs}] (below num_envs for EnvPool's asynchronous mode) or 0"
        )));
    }
    if let Some(batch) = catalog::native_async_batch(options, num_envs) {
        // The native engine steps a whole group at a time: recv returns the first group done.
        if !num_envs.is_multiple_of(batch) || num_envs / batch > catalog::MAX_ASYNC_GROUPS {
            return Err(CoreError::InvalidOption(format!(
                "option 'batch_size' is {batch} with num_envs {num_envs}: the native engine steps a session's envs in \
                 groups of batch_size (each recv returns the first group done), so num_envs must be a multiple of \
                 batch_size, in at most {} groups; give such a batch_size, or engine='envpool' for any batch_size",
                catalog::MAX_ASYNC_GROUPS
            )));
        }
    }
    if let (Some(batch), Some(_)) = (catalog::async_batch(options, num_envs), extras.buffer) {
        // Transitions would be recorded per recv, in the order envs come back: not built.
        return Err(CoreError::InvalidSession(format!(
            "a session with batch_size {batch} below num_envs {num_envs} (EnvPool's asynchronous mode) keeps no replay \
             or rollout buffer: create it without one, or with batch_size 0"
        )));
    }
    Ok(())
}
