//! The server-side actor: a session's envs stepped by the server with a policy the learner sent
//! (SetPolicy), recorded into the session's buffer, so that a remote learner only streams batches.
//! The manager's entry points (SetPolicy, StartActing, StopActing: admission, charges, checks) are
//! in `manager/actor.rs`; the actor's state, its policy and its loop are here.
//!
//! The design follows the distributed agents that put acting next to the environments (Ape-X,
//! IMPALA, R2D2): the actor is one task per session, stepping every env at once; a new policy
//! version waits in the session's slot and is taken between two steps, so no step sees half a model;
//! each transition records the version that acted. Reverb's rate limiter
//! ([`radserve_replay::RateLimiter`], the one sample streams wait on) bounds how far acting may run
//! ahead of the learner's sampling.
//!
//! While the actor acts, the session's [`crate::session::Stepper`] is `Actor`: clients' resets and
//! steps are refused, and only the actor's own turns step it.

use std::path::PathBuf;
use std::sync::Mutex;
use std::time::Duration;

use radserve_policy::{Acted, ActionSpec, ObservationSpec, ObservationType, Policy, PolicyError};
use radserve_replay::RateLimiter;
use rand_chacha::ChaCha8Rng;
use tokio::sync::watch;

use crate::budget::Reservation;
use crate::error::CoreError;
use crate::space::{DType, Space};

mod run;
#[cfg(test)]
pub(crate) mod tests;

pub(crate) use run::Actor;

/// Episodes whose returns an actor keeps for DescribeSession.
pub const RECENT_EPISODES: usize = 100;
/// Consecutive failed steps (a simulator failing each time) after which the actor stops.
const MAX_FAILED_STEPS: u32 = 3;
/// The range of StartActing's steps_per_second (env steps per second over the session).
pub const MIN_STEPS_PER_SECOND: f64 = 0.01;
pub const MAX_STEPS_PER_SECOND: f64 = 1e9;

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

/// What an actor acts with: a policy in its runtime process (SetPolicy's), or, in core's tests, a
/// rule run in the server.
pub(crate) enum ActorPolicy {
    Runtime(Box<Policy>),
    #[cfg(test)]
    Scripted(tests::Scripted),
}

impl ActorPolicy {
    /// One step's actions for every env. In the policy's runtime process, awaited (never on the
    /// calling thread), within `acting.policy_call_timeout_s`.
    async fn act(&mut self, obs: &[u8], rng: &mut ChaCha8Rng, env_steps: u64, eval: bool) -> Result<Acted, PolicyError> {
        match self {
            ActorPolicy::Runtime(policy) => policy.act(obs, rng, env_steps, eval).await,
            #[cfg(test)]
            ActorPolicy::Scripted(scripted) => scripted.act(obs, env_steps),
        }
    }

    /// False once its runtime was stopped (past its memory or time): it cannot act again.
    fn usable(&self) -> bool {
        match self {
            ActorPolicy::Runtime(policy) => policy.usable(),
            #[cfg(test)]
            ActorPolicy::Scripted(_) => true,
        }
    }
}

/// A policy as the session holds it: its version, and the memory charged for it (returned when
/// the policy is dropped, its runtime process killed).
pub(crate) struct HeldPolicy {
    pub(crate) policy: ActorPolicy,
    pub(crate) version: u32,
    pub(crate) _charge: Reservation,
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
    /// Reverb's rate limiter ([`RateLimiter`]): past `min_size` transitions, inserts keep to
    /// `samples / samples_per_insert` within `error_buffer / samples_per_insert`.
    pub samples_per_insert: Option<f64>,
    pub error_buffer: f64,
    /// Transitions the buffer holds before the limiter applies (the learner's min_size).
    pub min_size: u64,
    /// Seed of the random actions and the heads' draws (None: the session's seed).
    pub seed: Option<u64>,
    /// Stop after this many episodes have ended since the start, or env steps taken.
    pub max_episodes: Option<u64>,
    pub max_env_steps: Option<u64>,
}

impl ActingRequest {
    /// Checks the request's numbers; its rate limiter, when it asks for one.
    pub(crate) fn check(&self) -> Result<Option<RateLimiter>, CoreError> {
        if let Some(rate) = self.steps_per_second {
            if !(MIN_STEPS_PER_SECOND..=MAX_STEPS_PER_SECOND).contains(&rate) {
                return Err(CoreError::OutOfBounds(format!(
                    "steps_per_second must be between {MIN_STEPS_PER_SECOND} and {MAX_STEPS_PER_SECOND:e}; got {rate}"
                )));
            }
        }
        self.samples_per_insert
            .map(|ratio| RateLimiter::new(self.min_size, ratio, self.error_buffer).map_err(CoreError::OutOfBounds))
            .transpose()
    }
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
    pub(crate) loading: tokio::sync::Mutex<()>,
}

impl ActorSlot {
    pub(crate) fn status(&self) -> ActingStatus {
        self.status.lock().expect("actor status lock").clone()
    }

    fn update(&self, change: impl FnOnce(&mut ActingStatus)) {
        change(&mut self.status.lock().expect("actor status lock"));
    }

    /// Makes `policy` the session's newest: a running actor takes it before its next step.
    pub(crate) fn install(&self, policy: HeldPolicy, head: &str) {
        let version = policy.version;
        *self.pending.lock().expect("policy lock") = Some(policy);
        self.update(|status| {
            status.policy_version = Some(version);
            status.head = Some(head.to_string());
        });
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

    /// Starts an actor with the newest policy: `hand_over` gives it the session and builds it, or
    /// refuses (the policy is then given back).
    pub(crate) fn start(&self, hand_over: impl FnOnce() -> Result<Actor, CoreError>) -> Result<(), CoreError> {
        let mut running = self.running.lock().expect("actor lock");
        // An actor being stopped has left `running` but is still giving the session back until its
        // state changes: a new one waits for that.
        if running.as_ref().is_some_and(|(_, task)| !task.is_finished()) || self.status().state == ActingState::Acting {
            return Err(CoreError::Acting("this session's actor is already acting; StopActing first".into()));
        }
        let Some(policy) = self.take_pending() else {
            return Err(CoreError::Acting("this session has no policy: SetPolicy before StartActing".into()));
        };
        let actor = match hand_over() {
            Ok(actor) => actor,
            Err(error) => {
                self.give_back(policy);
                return Err(error);
            }
        };
        self.update(|status| {
            *status = ActingStatus {
                state: ActingState::Acting,
                policy_version: status.policy_version,
                acting_version: status.acting_version,
                head: status.head.take(),
                ..ActingStatus::default()
            }
        });
        let (stop, stopped) = watch::channel(false);
        let task = tokio::spawn(actor.run(policy, stopped));
        *running = Some((stop, task));
        Ok(())
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

pub(crate) fn observation_spec(space: &Space, num_envs: usize) -> Result<ObservationSpec, CoreError> {
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

pub(crate) fn action_spec(space: &Space) -> Result<ActionSpec, CoreError> {
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
