//! A session: a vector of environments of one id, in groups hosted by the simulators, whose
//! observations are frame-stacked here in the server (frames travel from the simulators once).
//!
//! Autoreset is "same-step" (EnvPool, gymnasium's `AutoresetMode.SAME_STEP`): the step that ends an
//! episode returns the first observation of the next one, and the last observation of the ended
//! episode separately, as `final_obs`.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};

use radserve_augment::ImagePlan;
use radserve_replay::ReplayBuffer;

use crate::catalog::{async_batch, engine_is_envpool, EnvId, Options};
use crate::error::CoreError;
use crate::metrics::CoreMetrics;
use crate::infos::Infos;
use crate::simulators::{EnvGroup, EnvSpec, FrameLayout, PendingStep, SimulatorError, Simulators};
use crate::space::Space;

mod async_mode;
mod recovery;
mod single;
mod stacking;
mod sync;
#[cfg(test)]
mod tests;

/// A step whose observations reach this many bytes (every env's stack, before the view) does its
/// copies (stacking, replay recording, the view) outside tokio's worker: below it the copies take
/// microseconds, less than handing the worker over would cost.
const COPY_OFF_WORKER_BYTES: usize = 1 << 20;

/// Runs `copy` (the synchronous part of a step: tens of MiB of memcpy for a large pixel session) where
/// it does not hold up other sessions' tasks: with `block_in_place` when the step moves at least
/// `COPY_OFF_WORKER_BYTES` and the runtime is multi-threaded (tokio hands this worker's queue to
/// another thread for the duration), inline otherwise (small steps; the core's current-thread tests).
pub(crate) fn copying<R>(bytes: usize, copy: impl FnOnce() -> R) -> R {
    use tokio::runtime::{Handle, RuntimeFlavor};
    let multi_threaded = Handle::try_current().is_ok_and(|handle| handle.runtime_flavor() == RuntimeFlavor::MultiThread);
    if bytes >= COPY_OFF_WORKER_BYTES && multi_threaded {
        tokio::task::block_in_place(copy)
    } else {
        copy()
    }
}

pub use single::{EnvEnd, EnvStep};

/// What a step that ends an episode returns (gymnasium's `AutoresetMode` names the same choices).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AutoresetMode {
    /// The ending step already returns the next episode's first observation, and the ended
    /// episode's last one as `final_obs` (EnvPool; gymnasium's `SAME_STEP`).
    SameStep,
}

impl AutoresetMode {
    /// The name clients see (`SessionInfo.autoreset_mode`).
    pub fn name(self) -> &'static str {
        match self {
            AutoresetMode::SameStep => "same-step",
        }
    }
}

/// The counters of a session that change as it acts, readable without its lock.
#[derive(Debug, Default)]
pub struct SessionStats {
    pub seed: AtomicU64,
    pub total_env_steps: AtomicU64,
    pub episodes_completed: AtomicU64,
}

/// What a reset resets and how it seeds (gymnasium's `reset(seed=..., options={"reset_mask": ...})`).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ResetSpec {
    /// Re-seed env i with `seed + i`.
    pub seed: Option<u64>,
    /// Or one seed per env (`num_envs` of them).
    pub env_seeds: Option<Vec<u64>>,
    /// Reset only these envs (`num_envs` entries, at least one true); None: every env.
    pub mask: Option<Vec<bool>>,
}

pub struct SessionConfig {
    pub env: EnvId,
    pub num_envs: usize,
    pub seed: u64,
    /// Resolved options (defaults included).
    pub options: Options,
    pub frame_stack: usize,
}

/// An episode that ended in a step.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeEnd {
    pub env_index: usize,
    pub episode_return: f64,
    pub episode_length: u64,
    pub terminated: bool,
    pub truncated: bool,
    pub error: Option<String>,
}

#[derive(Debug, Default)]
pub struct StepOutcome {
    /// [num_envs, *observation shape], raw bytes.
    pub obs: Vec<u8>,
    pub rewards: Vec<f64>,
    pub terminated: Vec<bool>,
    pub truncated: Vec<bool>,
    pub episodes: Vec<EpisodeEnd>,
    /// [episodes.len(), *observation shape]: the last observation of each ended episode.
    pub final_obs: Vec<u8>,
    /// The envs' own info dicts from the step (gymnasium's `info`), of the envs that returned one.
    pub step_infos: Infos,
    /// The info dicts of the resets made in the step (same-step autoreset, a simulator that raised,
    /// a lost worker's group rebuilt), of the envs that returned one.
    pub reset_infos: Infos,
}

pub struct Session {
    pub config: SessionConfig,
    /// One frame of one environment.
    pub frame_spec: EnvSpec,
    /// One (stacked) observation of one environment.
    pub observation_space: Space,
    groups: Vec<Box<dyn EnvGroup>>,
    layout: FrameLayout,
    /// The stacked observation of every env, oldest frame first.
    stacks: Vec<u8>,
    episode_returns: Vec<f64>,
    episode_lengths: Vec<u64>,
    /// Each env's seed: what it was last seeded with (seed + i at creation).
    seeds: Vec<u64>,
    needs_reset: bool,
    /// Step calls so far: the step index recorded with each transition.
    pub step_calls: u64,
    /// Where every frame and transition is recorded, when the session keeps a replay buffer.
    replay: Option<Arc<RwLock<ReplayBuffer>>>,
    /// Its counters (env steps, episodes), kept only here: Describe reads them while a step holds
    /// the session (no lock needed).
    pub stats: Arc<SessionStats>,
    /// The evaluation view observations are returned through (replay keeps the raw frames).
    view: Option<ImagePlan>,
    /// The reset info dicts of the envs the last reset reset.
    reset_infos: Infos,
    /// Where its steps and resets are counted (the manager's, shared by every session).
    metrics: Arc<CoreMetrics>,
    /// Asynchronous mode: envs sent an action (or reset) whose result `recv` has not returned yet.
    in_flight: Vec<bool>,
    /// Asynchronous mode: envs whose next result is a reset's first frame, not a step.
    resetting: Vec<bool>,
    /// The native engine's asynchronous mode (groups of `batch_size` envs, each sent and returned
    /// whole): each group's step in flight.
    group_steps: Vec<Option<PendingStep>>,
    /// The same: groups whose async reset is done and not yet returned by `recv`, with their reset
    /// infos, in order.
    group_resets: VecDeque<(usize, Infos)>,
    /// Who steps it: its clients, or the server's actor (StartActing), whose turns are the only
    /// resets and steps allowed until it stops.
    stepper: Stepper,
}

/// Who steps a session. Changed only through [`Session::hand_to_actor`], [`Session::hand_back`] and
/// the actor's own [`Session::reset_as_actor`] / [`Session::step_as_actor`].
#[derive(Clone, Debug, Default, PartialEq)]
pub enum Stepper {
    /// Its clients' reset and step calls (the default).
    #[default]
    Clients,
    /// The server's actor; `turn` is set during the actor's own reset or step.
    Actor { turn: Option<ActorTurn> },
}

/// The actor's reset or step in progress.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ActorTurn {
    /// What acted in the step (None: a reset, or random actions), recorded with each transition.
    pub acted: Option<ActedStamp>,
}

/// A server-side policy's step: its version and, per env, the action's log-probability and the
/// model's value.
#[derive(Clone, Debug, PartialEq)]
pub struct ActedStamp {
    pub version: i32,
    pub log_prob: Vec<f32>,
    pub value: Option<Vec<f32>>,
}

impl ActedStamp {
    pub fn by(&self, env: usize) -> radserve_replay::ActedBy {
        radserve_replay::ActedBy {
            version: self.version,
            log_prob: self.log_prob.get(env).copied().unwrap_or(0.0),
            value: self.value.as_ref().and_then(|values| values.get(env).copied()).unwrap_or(0.0),
        }
    }
}

impl Session {
    /// Builds the environments in the simulators (env i seeded seed + i) and waits for their first
    /// reset before stepping.
    pub async fn create(simulators: &dyn Simulators, config: SessionConfig) -> Result<Session, CoreError> {
        let mut worker_options = config.options.clone();
        worker_options.remove(crate::catalog::FRAME_STACK);
        let seeds = (0..config.num_envs as u64).map(|i| config.seed + i).collect();
        let (frame_spec, groups) =
            simulators.create_groups(&config.env, &worker_options, seeds).await.map_err(|error| match error {
                SimulatorError::Refused(message) => CoreError::CreateFailed { env_id: config.env.full(), message },
                other @ (SimulatorError::Failed(_)
                | SimulatorError::Lost(_)
                | SimulatorError::Unavailable(_)
                | SimulatorError::OutOfResources(_)) => other.into(),
            })?;
        let layout = FrameLayout { frame_bytes: frame_spec.observation.num_bytes() };
        let (config_seed, config_num_envs) = (config.seed, config.num_envs);
        // EnvPool's asynchronous mode runs in one process (EnvPool's); the native engine's steps groups
        // of batch_size envs whole.
        let misfit = match async_batch(&config.options, config.num_envs) {
            Some(_) if engine_is_envpool(&config.options) => (groups.len() != 1).then(|| {
                format!(
                    "a session of engine 'envpool' with a batch_size below num_envs must be hosted by one simulator \
                     process; {} hosts it in {}",
                    config.env.full(),
                    groups.len()
                )
            }),
            Some(batch) => groups.iter().any(|group| group.envs().len() != batch).then(|| {
                format!(
                    "a session with batch_size {batch} steps its envs in groups of {batch}; {} built groups of {:?} envs",
                    config.env.full(),
                    groups.iter().map(|group| group.envs().len()).collect::<Vec<_>>()
                )
            }),
            None => None,
        };
        if let Some(message) = misfit {
            let mut groups = groups;
            for group in &mut groups {
                group.close().await;
            }
            return Err(CoreError::InvalidSession(message));
        }
        let group_count = groups.len();
        Ok(Session {
            observation_space: frame_spec.observation.stacked(config.frame_stack),
            stacks: vec![0; config.num_envs * config.frame_stack * layout.frame_bytes],
            episode_returns: vec![0.0; config.num_envs],
            episode_lengths: vec![0; config.num_envs],
            seeds: (0..config.num_envs as u64).map(|i| config_seed + i).collect(),
            config,
            frame_spec,
            groups,
            layout,
            needs_reset: true,
            step_calls: 0,
            replay: None,
            stats: Arc::new(SessionStats { seed: AtomicU64::new(config_seed), ..SessionStats::default() }),
            view: None,
            reset_infos: Infos::default(),
            metrics: Arc::default(),
            in_flight: vec![false; config_num_envs],
            resetting: vec![false; config_num_envs],
            group_steps: (0..group_count).map(|_| None).collect(),
            group_resets: VecDeque::new(),
            stepper: Stepper::Clients,
        })
    }

    /// Count this session's steps and resets in `metrics` (the manager's) from now on.
    pub fn with_metrics(mut self, metrics: Arc<CoreMetrics>) -> Session {
        self.metrics = metrics;
        self
    }

    pub fn num_envs(&self) -> usize {
        self.config.num_envs
    }

    /// Env steps taken since the session was created (continued from a snapshot's).
    pub fn total_env_steps(&self) -> u64 {
        self.stats.total_env_steps.load(Ordering::Relaxed)
    }

    /// Episodes ended since the session was created (continued from a snapshot's).
    pub fn episodes_completed(&self) -> u64 {
        self.stats.episodes_completed.load(Ordering::Relaxed)
    }

    /// A session whose replay was restored from a snapshot continues the counters it was taken
    /// with: step indices after those of the restored transitions, and the totals Describe shows.
    pub fn continue_from(&mut self, counters: radserve_replay::snapshot::SessionCounters) {
        self.step_calls = self.step_calls.max(counters.step_calls);
        self.stats.total_env_steps.store(counters.total_env_steps, Ordering::Relaxed);
        self.stats.episodes_completed.store(counters.episodes_completed, Ordering::Relaxed);
    }

    /// Refuses a client's reset or step while the server's actor steps the session.
    pub(crate) fn refuse_while_acting(&self, what: &str) -> Result<(), CoreError> {
        if let Stepper::Actor { turn: None } = self.stepper {
            return Err(CoreError::Acting(format!(
                "this session is stepped by the server's actor (StartActing): {what} is refused until StopActing; \
                 its transitions arrive through SampleBatches"
            )));
        }
        Ok(())
    }

    /// Who steps the session now.
    pub fn stepper(&self) -> &Stepper {
        &self.stepper
    }

    /// The server's actor takes the session over: clients' resets and steps are refused from now on.
    pub(crate) fn hand_to_actor(&mut self) {
        self.stepper = Stepper::Actor { turn: None };
    }

    /// The actor stopped: clients step the session again.
    pub(crate) fn hand_back(&mut self) {
        self.stepper = Stepper::Clients;
    }

    /// The actor's reset of every env.
    pub(crate) async fn reset_as_actor(&mut self) -> Result<Vec<u8>, CoreError> {
        self.stepper = Stepper::Actor { turn: Some(ActorTurn::default()) };
        let reset = self.reset(None).await;
        self.stepper = Stepper::Actor { turn: None };
        reset
    }

    /// The actor's step of every env, each transition recorded with `acted`.
    pub(crate) async fn step_as_actor(
        &mut self,
        dtype: crate::space::DType,
        shape: &[usize],
        actions: &[u8],
        acted: Option<ActedStamp>,
    ) -> Result<StepOutcome, CoreError> {
        self.stepper = Stepper::Actor { turn: Some(ActorTurn { acted }) };
        let outcome = self.step(dtype, shape, actions).await;
        self.stepper = Stepper::Actor { turn: None };
        outcome
    }

    /// What acted in the step in progress, when the actor takes it with a policy.
    pub(crate) fn acted(&self) -> Option<&ActedStamp> {
        match &self.stepper {
            Stepper::Actor { turn: Some(ActorTurn { acted }) } => acted.as_ref(),
            Stepper::Clients | Stepper::Actor { turn: None } => None,
        }
    }

    /// Every env's current stacked observation, through the view (what the last reset or step
    /// returned).
    pub fn current_observations(&self) -> Vec<u8> {
        self.viewed(&self.stacks)
    }

    /// Whether the server's actor is stepping this session.
    pub fn is_acting(&self) -> bool {
        matches!(self.stepper, Stepper::Actor { .. })
    }

    /// Whether the session must be reset (every env) before it steps: new, or after a failed step.
    pub fn needs_reset(&self) -> bool {
        self.needs_reset
    }

    /// The reset info dicts of the envs the last reset reset, for those that returned a non-empty one.
    pub fn reset_infos(&self) -> &Infos {
        &self.reset_infos
    }

    /// Record every frame and transition from now on into `replay` (from the next reset).
    pub fn attach_replay(&mut self, replay: Arc<RwLock<ReplayBuffer>>) {
        self.replay = Some(replay);
    }

    pub fn replay(&self) -> Option<&Arc<RwLock<ReplayBuffer>>> {
        self.replay.as_ref()
    }

    /// The seeds of the envs of group `index`.
    fn group_seeds(&self, index: usize) -> Vec<u64> {
        self.groups[index].envs().map(|env| self.seeds[env]).collect()
    }

    fn end_episode(&mut self, env: usize, terminated: bool, truncated: bool, error: Option<String>) -> EpisodeEnd {
        self.stats.episodes_completed.fetch_add(1, Ordering::Relaxed);
        let episode = EpisodeEnd {
            env_index: env,
            episode_return: self.episode_returns[env],
            episode_length: self.episode_lengths[env],
            terminated,
            truncated,
            error,
        };
        self.episode_returns[env] = 0.0;
        self.episode_lengths[env] = 0;
        episode
    }

    /// Releases the environments in their simulators.
    pub async fn close(&mut self) {
        for mut group in self.groups.drain(..) {
            group.close().await;
        }
    }
}

#[cfg(test)]
mod copy_tests {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    use std::time::{Duration, Instant};

    use super::{copying, COPY_OFF_WORKER_BYTES};

    /// On a runtime of one worker, a task spawned by a task that is copying runs during the copy only
    /// if the copy left the worker (the spawned task waits in that worker's queue otherwise).
    async fn spawned_task_ran_during_copy(bytes: usize, wait: Duration) -> bool {
        tokio::spawn(async move {
            let ran = Arc::new(AtomicBool::new(false));
            let flag = ran.clone();
            tokio::spawn(async move { flag.store(true, Ordering::SeqCst) });
            copying(bytes, || {
                let started = Instant::now();
                while !ran.load(Ordering::SeqCst) && started.elapsed() < wait {
                    std::thread::yield_now();
                }
                ran.load(Ordering::SeqCst)
            })
        })
        .await
        .unwrap()
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 1)]
    async fn large_copies_leave_the_worker_to_other_tasks_and_small_ones_stay() {
        assert!(spawned_task_ran_during_copy(COPY_OFF_WORKER_BYTES, Duration::from_secs(20)).await);
        assert!(!spawned_task_ran_during_copy(COPY_OFF_WORKER_BYTES - 1, Duration::from_millis(300)).await);
    }

    #[tokio::test]
    async fn a_current_thread_runtime_copies_inline() {
        assert_eq!(copying(COPY_OFF_WORKER_BYTES * 4, || 7), 7);
    }
}
