//! Server-side actors: a session's envs stepped by the server with a policy the learner sent
//! (SetPolicy), recorded into the session's buffer, so that a remote learner only streams batches.
//!
//! The design follows the distributed agents that put acting next to the environments (Ape-X,
//! IMPALA, R2D2): the actor is one task per session, stepping every env at once; a new policy
//! version waits in the session's slot and is taken between two steps, so no step sees half a model;
//! each transition records the version that acted. Reverb's rate limiter (`samples_per_insert` with
//! an error buffer) bounds how far acting may run ahead of the learner's sampling.

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use radserve_policy::{ActionSpec, Head, ObservationSpec, ObservationType, Policy, PolicyError, PolicySpec, RuntimeLauncher};
use radserve_replay::ReplayBuffer;
use tokio::sync::watch;
use tracing::{info, warn};

use super::{SessionManager, SharedSession};
use crate::budget::Reservation;
use crate::error::CoreError;
use crate::metrics::CoreMetrics;
use crate::principal::{log_id, Principal};
use crate::session::ActedStamp;
use crate::space::{DType, Space};

/// Episodes whose returns an actor keeps for DescribeSession.
pub const RECENT_EPISODES: usize = 100;
/// Consecutive failed steps (a simulator failing each time) after which the actor stops.
const MAX_FAILED_STEPS: u32 = 3;
/// The range of StartActing's steps_per_second (env steps per second over the session).
pub const MIN_STEPS_PER_SECOND: f64 = 0.01;
pub const MAX_STEPS_PER_SECOND: f64 = 1e9;
/// How often a rate-limited actor looks again at the learner's sampling.
const RATE_POLL: Duration = Duration::from_millis(2);

/// How the server runs policies (`[acting]` in the configuration).
#[derive(Clone, Debug)]
pub struct ActingConfig {
    /// libonnxruntime; None: the one of the onnxruntime wheel installed for `python`.
    pub library: Option<PathBuf>,
    /// The workers' Python, where the onnxruntime wheel is looked for.
    pub python: Option<PathBuf>,
    /// The radserve executable, run as `radserve policy-runtime` for each policy (None: this one).
    pub program: Option<PathBuf>,
    /// ONNX Runtime intra-op threads per policy.
    pub threads: usize,
    /// The largest model SetPolicy takes.
    pub max_model_bytes: usize,
    /// The data memory of each policy's runtime process (its RLIMIT_DATA), charged with the model's
    /// bytes to the session's owner while the policy is held.
    pub policy_memory_bytes: u64,
    /// A policy must be built (and run once) within this; each inference must answer within
    /// `call_timeout`.
    pub load_timeout: Duration,
    pub call_timeout: Duration,
}

/// The default data memory of a policy runtime: ONNX Runtime's own (~20 MiB of data before a model)
/// and RAD's pixel actor (12 MB of weights) at 8 envs of 9x84x84 peak at ~75 MiB; the rest is room
/// for wider actors and more envs.
pub const DEFAULT_POLICY_MEMORY_BYTES: u64 = 256 << 20;

impl Default for ActingConfig {
    fn default() -> Self {
        ActingConfig {
            library: None,
            python: None,
            program: None,
            threads: 1,
            max_model_bytes: 64 << 20,
            policy_memory_bytes: DEFAULT_POLICY_MEMORY_BYTES,
            load_timeout: Duration::from_secs(60),
            call_timeout: Duration::from_secs(30),
        }
    }
}

/// A policy as the session holds it: its version, and the memory charged for it (returned when
/// the policy is dropped, its runtime process killed).
pub(crate) struct HeldPolicy {
    policy: Policy,
    version: u32,
    _charge: Reservation,
}

/// What StartActing asks for.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ActingRequest {
    /// Env steps per second over the session (all envs together), at most; None: as fast as it goes.
    pub steps_per_second: Option<f64>,
    /// Env steps taken with uniformly random actions before the policy acts (SAC's warm-up).
    pub random_steps: u64,
    /// Act without exploration (tanh(mean), argmax, no noise), for evaluation.
    pub eval: bool,
    /// Reverb's rate limiter: keep inserts (transitions recorded) within
    /// `(samples + error_buffer) / samples_per_insert` once the buffer can be sampled.
    pub samples_per_insert: Option<f64>,
    pub error_buffer: f64,
    /// Transitions recorded before the limiter applies (the learner's min_size).
    pub min_size: u64,
    /// Seed of the random actions and the heads' draws (None: the session's seed).
    pub seed: Option<u64>,
    /// Stop after this many episodes have ended since the start, or env steps taken.
    pub max_episodes: Option<u64>,
    pub max_env_steps: Option<u64>,
}

/// Where an actor stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum ActingState {
    /// Never started (a policy may be set).
    #[default]
    Idle,
    Acting,
    /// Stopped by StopActing, or done (max_episodes / max_env_steps reached).
    Stopped,
    /// Stopped by an error: the policy produced a value that is not finite, or the envs kept failing.
    Failed,
}

impl ActingState {
    pub fn name(self) -> &'static str {
        match self {
            ActingState::Idle => "idle",
            ActingState::Acting => "acting",
            ActingState::Stopped => "stopped",
            ActingState::Failed => "failed",
        }
    }
}

/// A session's actor as DescribeSession shows it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ActingStatus {
    pub state: ActingState,
    /// The newest policy set (SetPolicy), and the one the last step acted with.
    pub policy_version: Option<u32>,
    pub acting_version: Option<u32>,
    pub head: Option<String>,
    /// Env steps the actor took (random ones included) since it last started, and episodes ended.
    pub env_steps: u64,
    pub episodes: u64,
    /// Returns of the last episodes ended while acting, oldest first.
    pub recent_returns: Vec<f64>,
    /// The env each of `recent_returns` ended in.
    pub recent_envs: Vec<u32>,
    /// Seconds spent in inference and in stepping the envs since the start.
    pub inference_seconds: f64,
    pub step_seconds: f64,
    /// Seconds the rate limiter held the actor back.
    pub limited_seconds: f64,
    /// Why it failed (state Failed), or the last step error it recovered from.
    pub error: Option<String>,
}

/// A policy as SetPolicy loaded it.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadedPolicy {
    pub opset: i64,
    pub ops: std::collections::BTreeMap<String, usize>,
    pub input: radserve_policy::model::Port,
    pub outputs: Vec<radserve_policy::model::Port>,
    pub has_value: bool,
}

/// One session's policies and actor.
#[derive(Default)]
pub(crate) struct ActorSlot {
    /// The newest policy, until the actor takes it (between two steps).
    pending: Mutex<Option<HeldPolicy>>,
    status: Mutex<ActingStatus>,
    /// The running actor: its stop signal and task.
    running: Mutex<Option<(watch::Sender<bool>, tokio::task::JoinHandle<()>)>>,
    /// Serializes SetPolicy calls (the version check and the swap).
    loading: tokio::sync::Mutex<()>,
}

impl ActorSlot {
    pub(crate) fn status(&self) -> ActingStatus {
        self.status.lock().expect("actor status lock").clone()
    }

    fn update(&self, change: impl FnOnce(&mut ActingStatus)) {
        change(&mut self.status.lock().expect("actor status lock"));
    }

    fn take_pending(&self) -> Option<HeldPolicy> {
        self.pending.lock().expect("policy lock").take()
    }

    /// The policy an actor stopped with goes back, unless a newer one waits.
    fn give_back(&self, policy: HeldPolicy) {
        let mut pending = self.pending.lock().expect("policy lock");
        if pending.is_none() {
            *pending = Some(policy);
        }
    }

    /// Stops the actor, if one runs, and waits until its last step is done.
    pub(crate) async fn stop(&self) {
        let running = self.running.lock().expect("actor lock").take();
        if let Some((stop, task)) = running {
            stop.send_replace(true);
            let _ = task.await;
        }
    }
}

fn observation_spec(space: &Space, num_envs: usize) -> Result<ObservationSpec, CoreError> {
    let dtype = match space.dtype() {
        DType::Uint8 => ObservationType::Uint8,
        DType::Float32 => ObservationType::Float32,
        DType::Float64 => ObservationType::Float64,
        other @ (DType::Int32 | DType::Int64 | DType::Bool) => {
            return Err(CoreError::Acting(format!("server-side policies take uint8 or float observations; this session's are {}", other.name())))
        }
    };
    Ok(ObservationSpec { num_envs, shape: space.shape().to_vec(), dtype })
}

fn action_spec(space: &Space) -> Result<ActionSpec, CoreError> {
    match space {
        Space::Discrete { n } => Ok(ActionSpec::Discrete { n: *n as usize }),
        Space::Box { dtype: dtype @ (DType::Float32 | DType::Float64), shape, low, high } => {
            Ok(ActionSpec::Box { dims: shape.iter().product(), low: low.clone(), high: high.clone(), float64: *dtype == DType::Float64 })
        }
        Space::Box { .. } => Err(CoreError::Acting(format!(
            "server-side policies act in Discrete or float Box action spaces; this session's is {}",
            space.describe()
        ))),
    }
}

impl SessionManager {
    /// Server-side policies: how they are loaded.
    pub fn with_acting(mut self, config: ActingConfig) -> SessionManager {
        self.acting = config;
        self
    }

    pub fn acting_config(&self) -> &ActingConfig {
        &self.acting
    }

    /// How policy runtimes start: ONNX Runtime's library found (the workers' Python asked where its
    /// wheel is, off the async workers) at the first SetPolicy that finds it, then kept.
    async fn launcher(&self) -> Result<RuntimeLauncher, CoreError> {
        let library = match self.onnxruntime.get() {
            Some(library) => library.clone(),
            None => {
                let (library, python) = (self.acting.library.clone(), self.acting.python.clone());
                let found = tokio::task::spawn_blocking(move || match (library, python) {
                    (Some(library), _) => Ok(library),
                    (None, Some(python)) => radserve_policy::library_of_python(&python),
                    (None, None) => Err(PolicyError::Unavailable("no [acting] onnxruntime_library and no workers' Python to find it in".into())),
                })
                .await
                .map_err(|error| CoreError::Host(format!("finding ONNX Runtime: {error}")))??;
                self.onnxruntime.get_or_init(|| found).clone()
            }
        };
        let program = match &self.acting.program {
            Some(program) => program.clone(),
            None => std::env::current_exe().map_err(|error| CoreError::Host(format!("locating the radserve executable: {error}")))?,
        };
        Ok(RuntimeLauncher {
            program,
            args: vec!["policy-runtime".into()],
            library,
            memory_bytes: self.acting.policy_memory_bytes,
            load_timeout: self.acting.load_timeout,
            call_timeout: self.acting.call_timeout,
        })
    }

    /// Loads a policy for the session (checked, built and run once on zeros) and makes it the
    /// session's newest: a running actor takes it before its next step.
    pub async fn set_policy(
        &self,
        caller: &Principal,
        session_id: &str,
        model: Vec<u8>,
        head: Head,
        version: u32,
    ) -> Result<LoadedPolicy, CoreError> {
        if model.len() > self.acting.max_model_bytes {
            return Err(CoreError::TooLarge(format!(
                "the model is {} bytes; this server takes models of at most {} bytes (acting.max_model_bytes)",
                model.len(),
                self.acting.max_model_bytes
            )));
        }
        let (slot, info) = {
            let registry = self.sessions.lock().expect("registry lock");
            let entry = self.touch(&registry, caller, session_id)?;
            (entry.actor.clone(), entry.info.clone())
        };
        let _loading = slot.loading.lock().await;
        if let Some(last) = slot.status().policy_version {
            if version <= last {
                return Err(CoreError::Acting(format!("policy version {version} is not newer than the session's version {last}; versions must grow")));
            }
        }
        let observations = observation_spec(&info.observation_space, info.num_envs)?;
        let actions = action_spec(&info.action_space)?;
        let launcher = self.launcher().await?;
        // Charged before the runtime starts: its memory limit and the model's bytes, which the
        // server holds while the policy is loaded.
        let charge = self.reserve_memory(caller, launcher.memory_bytes + model.len() as u64, "a policy (acting.policy_memory_bytes and the model)")?;
        let spec = PolicySpec { head, threads: self.acting.threads.max(1) };
        let head_name = spec.head.name();
        let policy = Policy::load(&launcher, &model, spec, observations, actions).await?;
        let loaded = LoadedPolicy {
            opset: policy.summary.opset,
            ops: policy.summary.ops.clone(),
            input: policy.summary.input.clone(),
            outputs: policy.summary.outputs.clone(),
            has_value: policy.has_value(),
        };
        info!(session = log_id(session_id), version, peak_mib = policy.peak_bytes() >> 20, "policy loaded in its runtime");
        *slot.pending.lock().expect("policy lock") = Some(HeldPolicy { policy, version, _charge: charge });
        slot.update(|status| {
            status.policy_version = Some(version);
            status.head = Some(head_name.to_string());
        });
        self.metrics.acting.policies.fetch_add(1, Ordering::Relaxed);
        info!(session = log_id(session_id), version, head = head_name, "policy set");
        Ok(loaded)
    }

    /// Starts the session's actor with its newest policy.
    pub async fn start_acting(&self, caller: &Principal, session_id: &str, request: ActingRequest) -> Result<ActingStatus, CoreError> {
        if let Some(rate) = request.steps_per_second {
            if !(MIN_STEPS_PER_SECOND..=MAX_STEPS_PER_SECOND).contains(&rate) {
                return Err(CoreError::OutOfBounds(format!(
                    "steps_per_second must be between {MIN_STEPS_PER_SECOND} and {MAX_STEPS_PER_SECOND:e}; got {rate}"
                )));
            }
        }
        if let Some(ratio) = request.samples_per_insert {
            if !(ratio.is_finite() && ratio > 0.0 && request.error_buffer.is_finite() && request.error_buffer >= 0.0) {
                return Err(CoreError::OutOfBounds(format!(
                    "samples_per_insert must be a positive number and error_buffer at least 0; got {ratio} and {}",
                    request.error_buffer
                )));
            }
        }
        let (slot, session, replay, closed) = {
            let registry = self.sessions.lock().expect("registry lock");
            let entry = self.touch(&registry, caller, session_id)?;
            (entry.actor.clone(), entry.session.clone(), entry.replay.clone(), entry.lease.closed.subscribe())
        };
        if request.samples_per_insert.is_some() && replay.is_none() {
            return Err(CoreError::Acting("samples_per_insert limits acting against the sampling of a buffer; this session keeps none".into()));
        }
        let mut running = slot.running.lock().expect("actor lock");
        // An actor being stopped has left `running` but is still giving the session back until its
        // state changes: a new one waits for that.
        if running.as_ref().is_some_and(|(_, task)| !task.is_finished()) || slot.status().state == ActingState::Acting {
            return Err(CoreError::Acting("this session's actor is already acting; StopActing first".into()));
        }
        let policy = slot.take_pending();
        let Some(policy) = policy else {
            return Err(CoreError::Acting("this session has no policy: SetPolicy before StartActing".into()));
        };
        let session_seed = {
            // The session's lock is free unless a client's call is in progress: refuse then, and
            // refuse a session whose mode the actor cannot step.
            let Ok(mut locked) = session.try_lock() else {
                slot.give_back(policy);
                return Err(CoreError::Acting("a call is stepping this session; StartActing once it returned".into()));
            };
            if let Some(batch) = locked.async_batch() {
                slot.give_back(policy);
                return Err(CoreError::Acting(format!(
                    "the actor steps every env at once; this session returns {batch} envs at a time (batch_size): create it without batch_size"
                )));
            }
            locked.acting = true;
            locked.config.seed
        };
        let seed = request.seed.unwrap_or(session_seed);
        slot.update(|status| {
            status.state = ActingState::Acting;
            status.env_steps = 0;
            status.episodes = 0;
            status.recent_returns.clear();
            status.recent_envs.clear();
            status.inference_seconds = 0.0;
            status.step_seconds = 0.0;
            status.limited_seconds = 0.0;
            status.error = None;
        });
        let (stop, stopped) = watch::channel(false);
        let actor = Actor {
            session,
            slot: slot.clone(),
            replay,
            request,
            rng: ChaCha8Rng::seed_from_u64(seed),
            metrics: self.metrics.clone(),
            session_id: session_id.to_string(),
        };
        let task = tokio::spawn(actor.run(policy, stopped, closed));
        *running = Some((stop, task));
        info!(session = log_id(session_id), "acting started");
        Ok(slot.status())
    }

    /// Stops the session's actor after its current step; clients may step the session again.
    pub async fn stop_acting(&self, caller: &Principal, session_id: &str) -> Result<ActingStatus, CoreError> {
        let slot = {
            let registry = self.sessions.lock().expect("registry lock");
            self.touch(&registry, caller, session_id)?.actor.clone()
        };
        slot.stop().await;
        Ok(slot.status())
    }
}

struct Actor {
    session: SharedSession,
    slot: Arc<ActorSlot>,
    replay: Option<Arc<RwLock<ReplayBuffer>>>,
    request: ActingRequest,
    rng: ChaCha8Rng,
    metrics: Arc<CoreMetrics>,
    session_id: String,
}

/// Why an actor loop ended.
enum Ended {
    Stopped,
    Done,
    Failed(String),
}

impl Actor {
    /// Acts until stopped, done or failed, then gives the session back to its clients. The loop runs
    /// in a task of its own, so that even a panic in it (a bug) ends as a failed actor whose session
    /// is usable again, never as a session refused for ever.
    async fn run(self, policy: HeldPolicy, stopped: watch::Receiver<bool>, closed: watch::Receiver<bool>) {
        let (session, slot, metrics, session_id) = (self.session.clone(), self.slot.clone(), self.metrics.clone(), self.session_id.clone());
        let ended = match tokio::spawn(self.act_owned(policy, stopped, closed)).await {
            Ok((ended, policy)) => {
                // A policy whose runtime was stopped (past its memory or time) is dropped, its
                // charge returned: StartActing then asks for a new one rather than failing again.
                if policy.policy.usable() {
                    slot.give_back(policy);
                }
                ended
            }
            Err(error) => Ended::Failed(format!("the actor stopped on an internal error: {error}")),
        };
        {
            let mut session = session.lock().await;
            session.acting = false;
            session.actor_turn = false;
            session.acted = None;
        }
        Self::record_end(&slot, &metrics, &session_id, ended);
    }

    async fn act_owned(mut self, mut policy: HeldPolicy, mut stopped: watch::Receiver<bool>, mut closed: watch::Receiver<bool>) -> (Ended, HeldPolicy) {
        let ended = self.act(&mut policy, &mut stopped, &mut closed).await;
        (ended, policy)
    }

    fn record_end(slot: &ActorSlot, metrics: &CoreMetrics, session_id: &str, ended: Ended) {
        let (state, error) = match ended {
            Ended::Stopped | Ended::Done => (ActingState::Stopped, None),
            Ended::Failed(message) => {
                warn!(session = log_id(session_id), error = %message, "acting failed");
                metrics.acting.failures.fetch_add(1, Ordering::Relaxed);
                (ActingState::Failed, Some(message))
            }
        };
        slot.update(|status| {
            status.state = state;
            if error.is_some() {
                status.error = error;
            }
        });
        info!(session = log_id(session_id), state = state.name(), "acting ended");
    }

    /// Waits until `stopped` or `closed` turns true or `until` passes: true when stopped.
    async fn pause(stopped: &mut watch::Receiver<bool>, closed: &mut watch::Receiver<bool>, until: tokio::time::Instant) -> bool {
        tokio::select! {
            _ = stopped.wait_for(|stop| *stop) => true,
            _ = closed.wait_for(|closed| *closed) => true,
            () = tokio::time::sleep_until(until) => false,
        }
    }

    /// A reset or step of the envs failed: the actor goes on (the error shown) until it is the
    /// `MAX_FAILED_STEPS`th in a row, which ends it.
    fn envs_failed(&self, failures: &mut u32, error: &CoreError) -> Option<Ended> {
        *failures += 1;
        if *failures >= MAX_FAILED_STEPS {
            return Some(Ended::Failed(format!("the envs failed {failures} times in a row; the last: {error}")));
        }
        self.slot.update(|status| status.error = Some(error.to_string()));
        None
    }

    /// Whether the rate limiter holds the next insert back (Reverb's SampleToInsertRatio: inserts may
    /// run ahead of samples / ratio by at most error_buffer / ratio).
    fn limited(&self, num_envs: u64) -> bool {
        let (Some(ratio), Some(replay)) = (self.request.samples_per_insert, &self.replay) else { return false };
        let counters = replay.read().expect("replay lock").counters();
        let inserts = counters.inserts + num_envs;
        if inserts <= self.request.min_size {
            return false;
        }
        let allowed = (counters.samples as f64 + self.request.error_buffer) / ratio + self.request.min_size as f64;
        inserts as f64 > allowed
    }

    async fn act(&mut self, policy: &mut HeldPolicy, stopped: &mut watch::Receiver<bool>, closed: &mut watch::Receiver<bool>) -> Ended {
        let (num_envs, action_space) = {
            let session = self.session.lock().await;
            (session.num_envs() as u64, session.frame_spec.action.clone())
        };
        let Ok(actions_spec) = action_spec(&action_space) else { return Ended::Failed("the action space is not one a policy acts in".into()) };
        let mut next_at = tokio::time::Instant::now();
        let mut failures = 0;
        let (mut env_steps, mut episodes) = (0u64, 0u64);
        loop {
            if *stopped.borrow() || *closed.borrow() {
                return Ended::Stopped;
            }
            if self.request.max_episodes.is_some_and(|max| episodes >= max) || self.request.max_env_steps.is_some_and(|max| env_steps >= max) {
                return Ended::Done;
            }
            if let Some(rate) = self.request.steps_per_second {
                if Self::pause(stopped, closed, next_at).await {
                    return Ended::Stopped;
                }
                next_at = next_at.max(tokio::time::Instant::now() - Duration::from_secs(1)) + Duration::from_secs_f64(num_envs as f64 / rate);
            }
            let limited_from = Instant::now();
            while self.limited(num_envs) {
                if Self::pause(stopped, closed, tokio::time::Instant::now() + RATE_POLL).await {
                    return Ended::Stopped;
                }
            }
            let limited = limited_from.elapsed().as_secs_f64();
            if let Some(newer) = self.slot.take_pending() {
                *policy = newer;
            }
            let mut session = self.session.lock().await;
            session.actor_turn = true;
            let started = Instant::now();
            if session.needs_reset() {
                if let Err(error) = session.reset(None).await {
                    session.actor_turn = false;
                    if let Some(ended) = self.envs_failed(&mut failures, &error) {
                        return ended;
                    }
                    continue;
                }
            }
            let obs = session.current_observations();
            let inference_started = Instant::now();
            let random = env_steps < self.request.random_steps;
            let (actions, stamp) = if random {
                (actions_spec.random(num_envs as usize, &mut self.rng), None)
            } else {
                let HeldPolicy { policy: model, version, .. } = policy;
                let eval = self.request.eval;
                let total = session.total_env_steps;
                // In the policy's runtime process, awaited (never on this thread), within
                // acting.policy_call_timeout_s.
                match model.act(&obs, &mut self.rng, total, eval).await {
                    Ok(acted) => {
                        let stamp = ActedStamp { version: *version as i32, log_prob: acted.log_prob, value: acted.value };
                        (acted.actions, Some(stamp))
                    }
                    Err(error) => {
                        session.actor_turn = false;
                        return Ended::Failed(error.to_string());
                    }
                }
            };
            let inference = if random { 0.0 } else { inference_started.elapsed().as_secs_f64() };
            let version = stamp.as_ref().map(|stamp| stamp.version as u32);
            session.acted = stamp;
            let shape: Vec<usize> = std::iter::once(num_envs as usize).chain(action_space.shape().iter().copied()).collect();
            let outcome = session.step(action_space.dtype(), &shape, &actions).await;
            session.acted = None;
            session.actor_turn = false;
            drop(session);
            let step_seconds = started.elapsed().as_secs_f64() - inference;
            match outcome {
                Ok(outcome) => {
                    failures = 0;
                    env_steps += num_envs;
                    episodes += outcome.episodes.len() as u64;
                    self.metrics.acting.env_steps.fetch_add(num_envs, Ordering::Relaxed);
                    self.metrics.acting.add_inference(inference);
                    self.slot.update(|status| {
                        status.env_steps = env_steps;
                        status.episodes = episodes;
                        if version.is_some() {
                            status.acting_version = version;
                        }
                        status.inference_seconds += inference;
                        status.step_seconds += step_seconds;
                        status.limited_seconds += limited;
                        status.recent_returns.extend(outcome.episodes.iter().map(|episode| episode.episode_return));
                        status.recent_envs.extend(outcome.episodes.iter().map(|episode| episode.env_index as u32));
                        let old = status.recent_returns.len().saturating_sub(RECENT_EPISODES);
                        status.recent_returns.drain(..old);
                        status.recent_envs.drain(..old);
                    });
                }
                Err(error) => {
                    if let Some(ended) = self.envs_failed(&mut failures, &error) {
                        return ended;
                    }
                }
            }
        }
    }
}
