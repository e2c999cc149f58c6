//! A session: a vector of environments of one id, in groups hosted by the simulators, whose
//! observations are frame-stacked here in the server (frames travel from the simulators once).
//!
//! Autoreset is "same-step" (EnvPool, gymnasium's `AutoresetMode.SAME_STEP`): the step that ends an
//! episode returns the first observation of the next one, and the last observation of the ended
//! episode separately, as `final_obs`.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};
use std::task::Poll;

use futures_util::future::join_all;
use radserve_augment::{Augmentation, Draws, FrameShape, ImagePlan, Pipeline};
use radserve_replay::{RecordedStep, ReplayBuffer};

use crate::catalog::{async_batch, engine_is_envpool, native_async_batch, EnvId, Options};
use crate::error::CoreError;
use crate::metrics::CoreMetrics;
use crate::simulators::{EnvGroup, EnvSpec, FrameLayout, GroupInfo, PendingStep, ResetInfos, SimulatorError, Simulators, StepResult};
use crate::space::{DType, Space};

/// Largest seed + num_envs: dm_control and ProcGen seeds are 32-bit signed integers.
pub const MAX_SEED: u64 = i32::MAX as u64;

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

/// One group's part of a reset: its envs' seeds (if re-seeded) and mask (if partial).
type GroupReset = (Option<Vec<u64>>, Option<Vec<bool>>);

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
    /// The envs' own info dicts (JSON text from the simulators), for the envs that returned any.
    pub infos: Vec<EnvInfo>,
}

/// An env's own info dicts from one step: the step's, and (when the step ended its episode) the
/// reset's, as JSON text the simulator wrote; the server only carries them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EnvInfo {
    pub env_index: usize,
    pub step: Option<String>,
    pub reset: Option<String>,
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
    pub total_env_steps: u64,
    pub episodes_completed: u64,
    /// Step calls so far: the step index recorded with each transition.
    pub step_calls: u64,
    /// Where every frame and transition is recorded, when the session keeps a replay buffer.
    replay: Option<Arc<RwLock<ReplayBuffer>>>,
    /// What Describe reads while a step holds the session (no lock needed).
    pub stats: Arc<SessionStats>,
    /// The evaluation view observations are returned through (replay keeps the raw frames).
    view: Option<ImagePlan>,
    /// The reset info dicts of the envs the last reset reset (env index, JSON text).
    reset_infos: Vec<(usize, String)>,
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
    group_resets: VecDeque<(usize, ResetInfos)>,
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
            total_env_steps: 0,
            episodes_completed: 0,
            step_calls: 0,
            replay: None,
            stats: Arc::new(SessionStats { seed: AtomicU64::new(config_seed), ..SessionStats::default() }),
            view: None,
            reset_infos: Vec::new(),
            metrics: Arc::default(),
            in_flight: vec![false; config_num_envs],
            resetting: vec![false; config_num_envs],
            group_steps: (0..group_count).map(|_| None).collect(),
            group_resets: VecDeque::new(),
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

    /// Whether the session must be reset (every env) before it steps: new, or after a failed step.
    pub fn needs_reset(&self) -> bool {
        self.needs_reset
    }

    /// The reset info dicts (env index, JSON text) of the envs the last reset reset, for those that
    /// returned a non-empty one.
    pub fn reset_infos(&self) -> &[(usize, String)] {
        &self.reset_infos
    }

    /// Steps taken in each env's current episode (0: at an episode's first observation).
    pub fn episode_lengths(&self) -> &[u64] {
        &self.episode_lengths
    }

    /// Every env's current stacked observation `[num_envs, ...]`, as the last reset or step returned
    /// it (through the view, if any); None before the first reset.
    pub fn observations(&self) -> Option<Vec<u8>> {
        (!self.needs_reset).then(|| self.viewed(&self.stacks))
    }

    /// Return observations through `view` (a centre crop or centre translate, RAD's evaluation
    /// views), so that a policy trained on augmented crops acts on the matching view.
    pub fn set_view(&mut self, text: &str) -> Result<(), CoreError> {
        let invalid = |message: String| CoreError::InvalidView { text: text.to_string(), message };
        let pipeline = Pipeline::parse(text).map_err(|error| invalid(error.to_string()))?;
        if let Some(stage) = pipeline
            .stages()
            .iter()
            .find(|stage| !matches!(stage, Augmentation::CenterCrop { .. } | Augmentation::CenterTranslate { .. }))
        {
            return Err(invalid(format!("only center_crop and center_translate are views; {stage} is random")));
        }
        let frame = &self.frame_spec.observation;
        let (DType::Uint8, &[channels, height, width]) = (frame.dtype(), frame.shape()) else {
            return Err(invalid(format!("views apply to image observations; this session observes {}", frame.describe())));
        };
        let shape = FrameShape::new(self.config.frame_stack, channels, height, width);
        let plan = ImagePlan::new(&pipeline, shape).map_err(|error| invalid(error.to_string()))?;
        let out = plan.output_shape();
        self.observation_space = Space::Box {
            dtype: DType::Uint8,
            shape: vec![out.planes(), out.height, out.width],
            low: vec![0.0],
            high: vec![255.0],
        };
        self.view = (!plan.stages().is_empty()).then_some(plan);
        Ok(())
    }

    /// Stacked observations `[n, ...]` as the client receives them: through the view, if any.
    fn viewed(&self, stacks: &[u8]) -> Vec<u8> {
        let Some(view) = &self.view else { return stacks.to_vec() };
        let samples = stacks.len() / view.input_shape().sample_len();
        let mut out = vec![0; samples * view.output_shape().sample_len()];
        view.apply(stacks, &mut out, &Draws::new(0)).expect("buffers sized from the plan");
        out
    }

    /// Record every frame and transition from now on into `replay` (from the next reset).
    pub fn attach_replay(&mut self, replay: Arc<RwLock<ReplayBuffer>>) {
        self.replay = Some(replay);
    }

    pub fn replay(&self) -> Option<&Arc<RwLock<ReplayBuffer>>> {
        self.replay.as_ref()
    }

    /// Record each env of group `index` (those `mask` marks, if given) starting an episode at its
    /// current frame, before the Step call `step_index`.
    fn record_first_frames(&self, index: usize, step_index: u64, mask: Option<&[bool]>) {
        let Some(replay) = &self.replay else { return };
        let mut replay = replay.write().expect("replay lock");
        let group = &self.groups[index];
        for (local, env) in group.envs().enumerate() {
            if mask.is_some_and(|mask| !mask[env]) {
                continue;
            }
            replay.abandon_episode(env);
            replay.record_first_frame(env, &group.frames()[self.layout.frame(local)], step_index);
        }
    }

    fn stack_bytes(&self) -> usize {
        self.config.frame_stack * self.layout.frame_bytes
    }

    /// The seeds of the envs of group `index`.
    fn group_seeds(&self, index: usize) -> Vec<u64> {
        self.groups[index].envs().map(|env| self.seeds[env]).collect()
    }

    /// Resets every environment (re-seeding env i with seed + i when a seed is given) and returns the
    /// stacked observations: the first frame repeated `frame_stack` times.
    pub async fn reset(&mut self, seed: Option<u64>) -> Result<Vec<u8>, CoreError> {
        self.reset_with(&ResetSpec { seed, ..ResetSpec::default() }).await
    }

    /// Resets the envs `spec` names (all, or a mask), seeded as it says, and returns every env's
    /// stacked observation (those reset: their first frame repeated `frame_stack` times).
    pub async fn reset_with(&mut self, spec: &ResetSpec) -> Result<Vec<u8>, CoreError> {
        self.require_sync("reset")?;
        let num_envs = self.num_envs();
        if let Some(mask) = &spec.mask {
            check_mask(mask, num_envs, "reset_mask")?;
            if !mask.iter().any(|&reset| reset) {
                return Err(CoreError::InvalidMask("reset_mask must mark at least one env (gymnasium's rule)".into()));
            }
            if self.needs_reset && mask.iter().any(|&reset| !reset) {
                return Err(CoreError::InvalidMask(
                    "a reset with a mask resets some envs of a session already reset; reset every env first".into(),
                ));
            }
        }
        let seeds = match (spec.seed, &spec.env_seeds) {
            (Some(_), Some(_)) => return Err(CoreError::InvalidMask("give a seed or one seed per env, not both".into())),
            (Some(seed), None) => {
                check_seed(seed, num_envs)?;
                Some((0..num_envs as u64).map(|i| seed + i).collect::<Vec<_>>())
            }
            (None, Some(seeds)) => {
                if seeds.len() != num_envs {
                    return Err(CoreError::InvalidMask(format!("{} per-env seeds for {num_envs} envs", seeds.len())));
                }
                if let Some(&seed) = seeds.iter().find(|&&seed| seed > MAX_SEED) {
                    return Err(CoreError::InvalidSeed { seed, num_envs: 1, max: MAX_SEED });
                }
                Some(seeds.clone())
            }
            (None, None) => None,
        };
        let masked = |env: usize| spec.mask.as_ref().is_none_or(|mask| mask[env]);
        if let Some(seeds) = &seeds {
            for env in (0..num_envs).filter(|&env| masked(env)) {
                self.seeds[env] = seeds[env];
            }
            if masked(0) {
                self.config.seed = self.seeds[0];
                self.stats.seed.store(self.seeds[0], Ordering::Relaxed);
            }
        }
        // Per group: its part of the mask (None: all of it), skipped when it resets nothing.
        let plans: Vec<Option<GroupReset>> = (0..self.groups.len())
            .map(|index| {
                let envs = self.groups[index].envs();
                let mask = spec.mask.as_ref().map(|mask| mask[envs.clone()].to_vec());
                if mask.as_ref().is_some_and(|mask| !mask.contains(&true)) {
                    return None;
                }
                Some((seeds.as_ref().map(|_| self.group_seeds(index)), mask))
            })
            .collect();
        let results = join_all(self.groups.iter_mut().zip(plans.iter().cloned()).map(|(group, plan)| async move {
            match plan {
                Some((seeds, mask)) => Some(group.reset(seeds, mask).await),
                None => None,
            }
        }))
        .await;
        // A group whose process was replaced was rebuilt from its seeds: it is reset whole, so every
        // env of it starts over (unmasked ones too: their simulator state went with the process).
        let mut whole = vec![spec.mask.is_none(); self.groups.len()];
        self.reset_infos.clear();
        for (index, result) in results.into_iter().enumerate() {
            let infos = match result {
                None => continue,
                Some(Ok(infos)) => infos,
                Some(Err(SimulatorError::Lost(_))) => {
                    whole[index] = true;
                    self.reset_group(index).await?
                }
                Some(Err(error)) => return Err(error.into()),
            };
            let start = self.groups[index].envs().start;
            self.reset_infos.extend(infos.into_iter().map(|(local, info)| (start + local as usize, info)));
        }
        self.reset_infos.sort_by_key(|(env, _)| *env);
        for index in 0..self.groups.len() {
            if plans[index].is_none() && !whole[index] {
                continue;
            }
            let mask = if whole[index] { None } else { spec.mask.as_deref() };
            self.fill_stacks_from_current(index, mask);
            self.record_first_frames(index, self.step_calls, mask);
            for env in self.groups[index].envs().filter(|&env| mask.is_none_or(|mask| mask[env])) {
                self.episode_returns[env] = 0.0;
                self.episode_lengths[env] = 0;
            }
        }
        if spec.mask.is_none() {
            self.needs_reset = false;
        }
        self.metrics.record_reset();
        Ok(self.viewed(&self.stacks))
    }

    /// Resets one group with its envs' seeds (after its process was replaced); its reset infos.
    async fn reset_group(&mut self, index: usize) -> Result<crate::simulators::ResetInfos, CoreError> {
        let seeds = self.group_seeds(index);
        Ok(self.groups[index].reset(Some(seeds), None).await?)
    }

    /// Sets each stack of a group (those `mask` marks, if given) to its env's current frame
    /// repeated (the stacking at reset).
    fn fill_stacks_from_current(&mut self, index: usize, mask: Option<&[bool]>) {
        let stack_bytes = self.stack_bytes();
        let group = &self.groups[index];
        for (local, env) in group.envs().enumerate() {
            if mask.is_some_and(|mask| !mask[env]) {
                continue;
            }
            fill_stack(&mut self.stacks[env * stack_bytes..][..stack_bytes], &group.frames()[self.layout.frame(local)]);
        }
    }

    /// Steps every environment with `actions` ([num_envs, *action shape] of the action dtype).
    pub async fn step(&mut self, dtype: DType, shape: &[usize], actions: &[u8]) -> Result<StepOutcome, CoreError> {
        self.step_except(dtype, shape, actions, None).await
    }

    /// Steps every environment but those `skip` marks (`num_envs` entries): a skipped env keeps its
    /// observation, gets reward 0 and no episode end, and nothing of it is recorded; its action is
    /// ignored (still checked). This is gymnasium NEXT_STEP's reset step, for a client whose env
    /// was already reset when its episode ended.
    pub async fn step_except(
        &mut self,
        dtype: DType,
        shape: &[usize],
        actions: &[u8],
        skip: Option<&[bool]>,
    ) -> Result<StepOutcome, CoreError> {
        self.require_sync("step")?;
        if self.needs_reset {
            return Err(CoreError::NotReset);
        }
        let started = std::time::Instant::now();
        validate_actions(&self.frame_spec.action, self.num_envs(), dtype, shape, actions)?;
        if let Some(skip) = skip {
            check_mask(skip, self.num_envs(), "skip")?;
        }
        let skip = skip.filter(|skip| skip.contains(&true));
        let action_bytes = self.frame_spec.action.num_bytes();
        let calls: Vec<(Vec<u8>, Option<Vec<bool>>)> = self
            .groups
            .iter()
            .map(|group| {
                let envs = group.envs();
                (actions[envs.start * action_bytes..envs.end * action_bytes].to_vec(), skip.map(|skip| skip[envs].to_vec()))
            })
            .collect();
        let results = join_all(self.groups.iter_mut().zip(calls).map(|(group, (slice, skip))| async move {
            match skip {
                // Nothing of this group steps: no call at all.
                Some(skip) if !skip.contains(&false) => {
                    let n = skip.len();
                    Ok(StepResult {
                        rewards: vec![0.0; n],
                        terminated: vec![false; n],
                        truncated: vec![false; n],
                        ..StepResult::default()
                    })
                }
                skip => group.step(slice, skip).await,
            }
        }))
        .await;
        let skipped = |env: usize| skip.is_some_and(|skip| skip[env]);
        let num_envs = self.num_envs();
        let mut outcome = StepOutcome {
            rewards: vec![0.0; num_envs],
            terminated: vec![false; num_envs],
            truncated: vec![false; num_envs],
            ..StepOutcome::default()
        };
        for (index, result) in results.into_iter().enumerate() {
            let group_len = self.groups[index].envs().len();
            let result = match result {
                // A group's answer sized for another group (a bug, or a broken worker) ends the step
                // cleanly instead of indexing past it below.
                Ok(result) if result.fits(group_len) => result,
                Ok(result) => {
                    self.needs_reset = true;
                    return Err(CoreError::Simulator(format!(
                        "worker answered a step of {group_len} envs with {} rewards, {} terminated and {} truncated flags",
                        result.rewards.len(),
                        result.terminated.len(),
                        result.truncated.len()
                    )));
                }
                // The group's process died, hung, or was replaced since this session last used it
                // (another session's step crashed it): its episodes end here.
                Err(SimulatorError::Lost(message)) => {
                    self.recover_lost_group(index, &message, &mut outcome).await?;
                    continue;
                }
                Err(error) => {
                    self.needs_reset = true;
                    return Err(error.into());
                }
            };
            let group_envs = self.groups[index].envs();
            outcome.infos.extend(result.infos.iter().filter(|info| !skipped(group_envs.start + info.env as usize)).map(|info| {
                EnvInfo { env_index: group_envs.start + info.env as usize, step: info.step.clone(), reset: info.reset.clone() }
            }));
            if let Some(replay) = &self.replay {
                // Recorded before the stacks move on; sync, so no lock is held across an await.
                let mut replay = replay.write().expect("replay lock");
                let group = &self.groups[index];
                for (local, env) in group_envs.clone().enumerate() {
                    if skipped(env) {
                        continue;
                    }
                    let ended = result.terminated[local] || result.truncated[local];
                    let next = if ended { self.layout.final_frame(local) } else { self.layout.frame(local) };
                    replay.record_step(
                        env,
                        &RecordedStep {
                            action: &actions[env * action_bytes..(env + 1) * action_bytes],
                            reward: result.rewards[local],
                            terminated: result.terminated[local],
                            truncated: result.truncated[local],
                            next_frame: &group.frames()[next],
                            step_index: self.step_calls,
                        },
                    );
                    if ended {
                        let first = &group.frames()[self.layout.frame(local)];
                        replay.record_first_frame(env, first, self.step_calls + 1);
                    }
                }
            }
            for (local, env) in group_envs.enumerate() {
                if !skipped(env) {
                    self.advance(index, local, env, &result, &mut outcome);
                }
            }
        }
        let stepped = (0..num_envs).filter(|&env| !skipped(env)).count() as u64;
        self.finish_step(stepped, started, &mut outcome);
        Ok(outcome)
    }

    /// The envs a `recv` returns at most, for a session in EnvPool's asynchronous mode (option
    /// `batch_size` below `num_envs`); None for a synchronous one.
    pub fn async_batch(&self) -> Option<usize> {
        async_batch(&self.config.options, self.config.num_envs)
    }

    fn require_async(&self, what: &str) -> Result<usize, CoreError> {
        self.async_batch().ok_or_else(|| {
            CoreError::InvalidSession(format!(
                "{what} is for sessions whose batch_size is below num_envs (EnvPool's asynchronous mode); this one \
                 steps every env at once (reset/step)"
            ))
        })
    }

    fn require_sync(&self, what: &str) -> Result<(), CoreError> {
        match self.async_batch() {
            Some(batch) => Err(CoreError::InvalidSession(format!(
                "this session returns {batch} of its {} envs at a time (batch_size): it is reset with async_reset and \
                 stepped with send/recv, not {what}",
                self.num_envs()
            ))),
            None => Ok(()),
        }
    }

    /// EnvPool's asynchronous mode: resets every env (env i re-seeded with seed + i when a seed is given);
    /// their first observations come back through `recv`, `batch_size` envs at a time.
    pub async fn async_reset(&mut self, seed: Option<u64>) -> Result<(), CoreError> {
        self.require_async("async_reset")?;
        let num_envs = self.num_envs();
        if let Some(seed) = seed {
            check_seed(seed, num_envs)?;
            self.seeds = (0..num_envs as u64).map(|i| seed + i).collect();
            self.config.seed = seed;
            self.stats.seed.store(seed, Ordering::Relaxed);
        }
        if let Err(error) = self.start_async_reset(seed.is_some()).await {
            self.needs_reset = true;
            return Err(error.into());
        }
        self.in_flight.fill(true);
        self.resetting.fill(true);
        self.episode_returns.fill(0.0);
        self.episode_lengths.fill(0);
        self.needs_reset = false;
        self.metrics.record_reset();
        Ok(())
    }

    /// Whether this is the native engine's asynchronous mode: groups of `batch_size` envs, each stepped
    /// whole by its worker, one group's step in flight while another's result is read (the session
    /// does the asynchronous part); otherwise EnvPool's, in its one group.
    fn steps_groups(&self) -> bool {
        native_async_batch(&self.config.options, self.config.num_envs).is_some()
    }

    /// Resets every env for `async_reset` (reseeded with the session's seeds when `seeded`).
    async fn start_async_reset(&mut self, seeded: bool) -> Result<(), SimulatorError> {
        if !self.steps_groups() {
            let seeds = seeded.then(|| self.group_seeds(0));
            return self.groups[0].async_reset(seeds).await;
        }
        // Steps in flight are dropped: their worker answers them before the reset (a worker runs its
        // requests in order), so the reset is what the envs' next results start from.
        self.group_steps.iter_mut().for_each(|step| *step = None);
        self.group_resets.clear();
        let seeds: Vec<Option<Vec<u64>>> = (0..self.groups.len()).map(|index| seeded.then(|| self.group_seeds(index))).collect();
        let results = join_all(self.groups.iter_mut().zip(seeds).map(|(group, seeds)| group.reset(seeds, None))).await;
        for (index, result) in results.into_iter().enumerate() {
            match result {
                Ok(infos) => self.group_resets.push_back((index, infos)),
                Err(error) => {
                    self.group_resets.clear();
                    return Err(error);
                }
            }
        }
        Ok(())
    }

    /// The native engine's asynchronous mode: starts the step of each group `sent` marks (whole).
    async fn start_group_steps(&mut self, actions: &[u8], sent: &[bool]) {
        let row = self.frame_spec.action.num_bytes();
        for index in 0..self.groups.len() {
            let envs = self.groups[index].envs();
            if sent[envs.start] {
                let slice = actions[envs.start * row..envs.end * row].to_vec();
                self.group_steps[index] = Some(self.groups[index].start_step(slice).await);
            }
        }
    }

    /// The native engine's asynchronous mode: the next group whose reset or step is done, and its
    /// result (every env of it ready).
    async fn next_group(&mut self) -> (usize, Result<(Vec<bool>, StepResult), SimulatorError>) {
        if let Some((index, infos)) = self.group_resets.pop_front() {
            let n = self.groups[index].envs().len();
            let result = StepResult {
                rewards: vec![0.0; n],
                terminated: vec![false; n],
                truncated: vec![false; n],
                errors: Vec::new(),
                infos: infos.into_iter().map(|(env, info)| GroupInfo { env, step: None, reset: Some(info) }).collect(),
            };
            return (index, Ok((vec![true; n], result)));
        }
        if self.group_steps.iter().all(Option::is_none) {
            // check_recv lets a recv through only with a whole group in flight.
            return (0, Err(SimulatorError::Failed("recv found no group stepping".into())));
        }
        let steps = &mut self.group_steps;
        let (index, result) = std::future::poll_fn(|context| {
            for (index, step) in steps.iter_mut().enumerate() {
                if let Some(future) = step {
                    if let Poll::Ready(result) = future.as_mut().poll(context) {
                        *step = None;
                        return Poll::Ready((index, result));
                    }
                }
            }
            Poll::Pending
        })
        .await;
        let n = self.groups[index].envs().len();
        (index, result.map(|result| (vec![true; n], result)))
    }

    /// The native engine's asynchronous mode sends whole groups.
    fn check_whole_groups(&self, sent: &[bool]) -> Result<(), CoreError> {
        for group in &self.groups {
            let envs = group.envs();
            if let Some(env) = envs.clone().find(|&env| sent[env] != sent[envs.start]) {
                let (part, missing) = if sent[env] { (env, envs.start) } else { (envs.start, env) };
                return Err(CoreError::InvalidMask(format!(
                    "the native engine steps this session's envs in groups of batch_size {} (envs {}..{} are one): \
                     send names whole groups, as recv returns them; env {part} is sent without env {missing}",
                    envs.len(),
                    envs.start,
                    envs.end
                )));
            }
        }
        Ok(())
    }

    /// EnvPool's asynchronous mode: starts the next step of the envs `sent` marks (`num_envs` entries;
    /// each one whose last result `recv` returned) with their rows of `actions` (every env's row, as
    /// in `step`; the others are checked and ignored), without waiting for it.
    pub async fn send(&mut self, dtype: DType, shape: &[usize], actions: &[u8], sent: &[bool]) -> Result<(), CoreError> {
        self.check_send(dtype, shape, actions, sent)?;
        if self.steps_groups() {
            self.start_group_steps(actions, sent).await;
        } else if let Err(error) = self.groups[0].send(actions.to_vec(), sent.to_vec()).await {
            self.needs_reset = true;
            return Err(error.into());
        }
        self.mark_sent(sent);
        Ok(())
    }

    /// `send` then `recv` in one round trip to the simulators (EnvPool's `step(action, env_id)` in
    /// its asynchronous mode). Refused, with nothing sent, when the recv could not be answered.
    pub async fn send_recv(
        &mut self,
        dtype: DType,
        shape: &[usize],
        actions: &[u8],
        sent: &[bool],
    ) -> Result<(Vec<bool>, StepOutcome), CoreError> {
        self.check_send(dtype, shape, actions, sent)?;
        let newly = sent.iter().filter(|&&sent| sent).count();
        self.check_recv(newly)?;
        let started = std::time::Instant::now();
        if self.steps_groups() {
            self.start_group_steps(actions, sent).await;
            self.mark_sent(sent);
            let (index, reply) = self.next_group().await;
            return self.finish_recv(index, reply, started);
        }
        let reply = self.groups[0].send_recv(actions.to_vec(), sent.to_vec()).await;
        self.mark_sent(sent);
        self.finish_recv(0, reply, started)
    }

    fn check_send(&self, dtype: DType, shape: &[usize], actions: &[u8], sent: &[bool]) -> Result<(), CoreError> {
        self.require_async("send")?;
        if self.needs_reset {
            return Err(CoreError::NotReset);
        }
        validate_actions(&self.frame_spec.action, self.num_envs(), dtype, shape, actions)?;
        check_mask(sent, self.num_envs(), "the mask of envs sent")?;
        if !sent.contains(&true) {
            return Err(CoreError::InvalidMask("send names no env: mark at least one".into()));
        }
        if self.steps_groups() {
            self.check_whole_groups(sent)?;
        }
        let waiting: Vec<usize> = (0..self.num_envs()).filter(|&env| sent[env] && self.in_flight[env]).collect();
        if !waiting.is_empty() {
            return Err(CoreError::InvalidMask(format!(
                "envs {waiting:?} are still stepping: send an env its next action after recv returned its last result"
            )));
        }
        Ok(())
    }

    fn mark_sent(&mut self, sent: &[bool]) {
        for (env, &sent) in sent.iter().enumerate() {
            self.in_flight[env] |= sent;
        }
    }

    /// The rows `send` takes for the actions of the envs `env_ids` names only (EnvPool's
    /// `send(action, env_id)`; `actions` is [len(env_ids), *action shape], row k for env
    /// `env_ids[k]`): every env's row, its shape, and the mask of envs sent.
    pub fn scatter_actions(
        &self,
        dtype: DType,
        shape: &[usize],
        actions: &[u8],
        env_ids: &[u64],
    ) -> Result<ScatteredActions, CoreError> {
        self.require_async("send")?;
        let num_envs = self.num_envs();
        if env_ids.is_empty() || env_ids.len() > num_envs {
            return Err(CoreError::InvalidMask(format!(
                "send names {} envs; a session of {num_envs} envs takes 1 to {num_envs} env ids",
                env_ids.len()
            )));
        }
        let mut sent = vec![false; num_envs];
        for &env in env_ids {
            match sent.get_mut(env as usize) {
                Some(seen) if !*seen => *seen = true,
                Some(_) => return Err(CoreError::InvalidMask(format!("send names env {env} twice"))),
                None => {
                    return Err(CoreError::InvalidMask(format!(
                        "send names env {env}; this session's env ids are 0 to {}",
                        num_envs - 1
                    )))
                }
            }
        }
        validate_actions(&self.frame_spec.action, env_ids.len(), dtype, shape, actions)?;
        // The unsent envs' rows repeat the first sent one (a valid action), and are ignored.
        let row = self.frame_spec.action.num_bytes();
        let mut rows = actions[..row].repeat(num_envs);
        for (k, &env) in env_ids.iter().enumerate() {
            rows[env as usize * row..][..row].copy_from_slice(&actions[k * row..][..row]);
        }
        let mut full_shape = shape.to_vec();
        full_shape[0] = num_envs;
        Ok((rows, full_shape, sent))
    }

    /// EnvPool's asynchronous mode: waits for the next `batch_size` envs whose step (or reset) is
    /// complete and returns which (`ready`) with the step's outcome laid out as `step`'s: every env's
    /// observation, the ready envs' rewards, flags, ended episodes and final observations (others:
    /// zero). Needs at least `batch_size` envs stepping; returns fewer only when some of those were
    /// already complete.
    pub async fn recv(&mut self) -> Result<(Vec<bool>, StepOutcome), CoreError> {
        self.check_recv(0)?;
        let started = std::time::Instant::now();
        let (index, reply) = if self.steps_groups() { self.next_group().await } else { (0, self.groups[0].recv().await) };
        self.finish_recv(index, reply, started)
    }

    /// Refuses a recv that would wait forever: fewer than a batch stepping, counting `sending` envs
    /// about to be sent.
    fn check_recv(&self, sending: usize) -> Result<(), CoreError> {
        let batch = self.require_async("recv")?;
        if self.needs_reset {
            return Err(CoreError::NotReset);
        }
        let stepping = self.in_flight.iter().filter(|&&env| env).count() + sending;
        if stepping < batch {
            return Err(CoreError::InvalidMask(format!(
                "recv returns {batch} envs at a time and {stepping} are stepping: send actions to at least {} more",
                batch - stepping
            )));
        }
        Ok(())
    }

    /// A recv's reply from group `index` (which of its envs are ready, and their results), checked
    /// and applied to the envs' stacks and episodes; returns which of the session's envs are ready.
    fn finish_recv(
        &mut self,
        index: usize,
        reply: Result<(Vec<bool>, StepResult), SimulatorError>,
        started: std::time::Instant,
    ) -> Result<(Vec<bool>, StepOutcome), CoreError> {
        let num_envs = self.num_envs();
        let envs = self.groups[index].envs();
        let (local_ready, result) = match reply {
            Ok((ready, result))
                if ready.len() == envs.len()
                    && result.fits(envs.len())
                    && ready.iter().zip(&self.in_flight[envs.clone()]).all(|(&ready, &stepping)| stepping || !ready) =>
            {
                (ready, result)
            }
            Ok((ready, _)) => {
                self.needs_reset = true;
                return Err(CoreError::Simulator(format!(
                    "worker answered a recv with {} of {} envs ready, or an env that was not stepping",
                    ready.len(),
                    envs.len()
                )));
            }
            Err(error) => {
                self.needs_reset = true;
                return Err(error.into());
            }
        };
        let mut outcome = StepOutcome {
            rewards: vec![0.0; num_envs],
            terminated: vec![false; num_envs],
            truncated: vec![false; num_envs],
            ..StepOutcome::default()
        };
        let mut ready = vec![false; num_envs];
        ready[envs.clone()].copy_from_slice(&local_ready);
        outcome.infos.extend(result.infos.iter().filter(|info| local_ready[info.env as usize]).map(|info| EnvInfo {
            env_index: envs.start + info.env as usize,
            step: info.step.clone(),
            reset: info.reset.clone(),
        }));
        // A ready env's first result after async_reset is its reset's first frame: its stack starts
        // from it. The others took a step.
        let reset: Vec<bool> = (0..num_envs).map(|env| ready[env] && std::mem::take(&mut self.resetting[env])).collect();
        self.fill_stacks_from_current(index, Some(&reset));
        let mut stepped = 0;
        for (local, env) in envs.enumerate().filter(|&(local, _)| local_ready[local]) {
            self.in_flight[env] = false;
            if !reset[env] {
                stepped += 1;
                self.advance(index, local, env, &result, &mut outcome);
            }
        }
        self.finish_step(stepped, started, &mut outcome);
        Ok((ready, outcome))
    }

    /// After a step or recv that stepped `stepped` envs since `started`: the counters and metrics, and
    /// the outcome's observations through the view.
    fn finish_step(&mut self, stepped: u64, started: std::time::Instant, outcome: &mut StepOutcome) {
        self.total_env_steps += stepped;
        let errors = outcome.episodes.iter().filter(|episode| episode.error.is_some()).count() as u64;
        self.metrics.record_step(self.config.env.family, stepped, started.elapsed(), outcome.episodes.len() as u64, errors);
        self.stats.total_env_steps.store(self.total_env_steps, Ordering::Relaxed);
        self.stats.episodes_completed.store(self.episodes_completed, Ordering::Relaxed);
        self.step_calls += 1;
        outcome.obs = self.viewed(&self.stacks);
        outcome.final_obs = self.viewed(&outcome.final_obs);
    }

    /// Env `env` (group `index`'s env `local`) took a step with `result`'s entry `local`: its reward and
    /// flags go into `outcome`, its stack moves on to its new frame, and when its episode ended the
    /// episode's last stacked observation goes into `outcome.final_obs` and the stack restarts from
    /// the next episode's first frame (same-step autoreset).
    fn advance(&mut self, index: usize, local: usize, env: usize, result: &StepResult, outcome: &mut StepOutcome) {
        let (reward, terminated, truncated) = (result.rewards[local], result.terminated[local], result.truncated[local]);
        outcome.rewards[env] = reward;
        outcome.terminated[env] = terminated;
        outcome.truncated[env] = truncated;
        self.episode_returns[env] += reward;
        self.episode_lengths[env] += 1;
        let stack_bytes = self.stack_bytes();
        let group = &self.groups[index];
        let frame = &group.frames()[self.layout.frame(local)];
        let stack = &mut self.stacks[env * stack_bytes..][..stack_bytes];
        if terminated || truncated {
            let final_frame = &group.frames()[self.layout.final_frame(local)];
            push_frame(stack, final_frame);
            outcome.final_obs.extend_from_slice(stack);
            fill_stack(stack, frame);
            let error = result.errors.iter().find(|(j, _)| *j as usize == local).map(|(_, m)| m.clone());
            outcome.episodes.push(self.end_episode(env, terminated, truncated, error));
        } else {
            push_frame(stack, frame);
        }
    }

    /// After a group's process was lost mid-step: its envs' episodes end as truncated with the error,
    /// their last observation is the stack before the step, and they start again from a reset.
    async fn recover_lost_group(
        &mut self,
        index: usize,
        message: &str,
        outcome: &mut StepOutcome,
    ) -> Result<(), CoreError> {
        let infos = match self.reset_group(index).await {
            Ok(infos) => infos,
            Err(error) => {
                self.needs_reset = true;
                return Err(error);
            }
        };
        let start = self.groups[index].envs().start;
        outcome.infos.extend(infos.into_iter().map(|(local, info)| EnvInfo {
            env_index: start + local as usize,
            step: None,
            reset: Some(info),
        }));
        let stack_bytes = self.stack_bytes();
        for env in self.groups[index].envs() {
            outcome.final_obs.extend_from_slice(&self.stacks[env * stack_bytes..(env + 1) * stack_bytes]);
            outcome.truncated[env] = true;
            self.episode_lengths[env] += 1;
            outcome.episodes.push(self.end_episode(env, false, true, Some(message.to_string())));
        }
        self.fill_stacks_from_current(index, None);
        // The crashed step has no next frame to record; the episodes restart from the new frames.
        self.record_first_frames(index, self.step_calls + 1, None);
        Ok(())
    }

    fn end_episode(&mut self, env: usize, terminated: bool, truncated: bool, error: Option<String>) -> EpisodeEnd {
        self.episodes_completed += 1;
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

/// Sets every slot of a stack to `frame` (a stack at its episode's first frame).
fn fill_stack(stack: &mut [u8], frame: &[u8]) {
    for slot in stack.chunks_exact_mut(frame.len()) {
        slot.copy_from_slice(frame);
    }
}

/// Drops the oldest frame of a stack and appends `frame`.
fn push_frame(stack: &mut [u8], frame: &[u8]) {
    stack.copy_within(frame.len().., 0);
    let tail = stack.len() - frame.len();
    stack[tail..].copy_from_slice(frame);
}

/// A mask has one entry per env.
fn check_mask(mask: &[bool], num_envs: usize, what: &str) -> Result<(), CoreError> {
    if mask.len() != num_envs {
        return Err(CoreError::InvalidMask(format!("{what} has {} entries; the session has {num_envs} envs", mask.len())));
    }
    Ok(())
}

/// Every env's row of actions, their shape, and the mask of envs sent (`Session::scatter_actions`).
pub type ScatteredActions = (Vec<u8>, Vec<usize>, Vec<bool>);

pub fn check_seed(seed: u64, num_envs: usize) -> Result<(), CoreError> {
    if seed.saturating_add(num_envs as u64) > MAX_SEED {
        return Err(CoreError::InvalidSeed { seed, num_envs, max: MAX_SEED });
    }
    Ok(())
}

/// Checks a batch of actions against the action space: dtype, shape, finiteness and bounds.
pub fn validate_actions(
    space: &Space,
    num_envs: usize,
    dtype: DType,
    shape: &[usize],
    data: &[u8],
) -> Result<(), CoreError> {
    let mut expected_shape = vec![num_envs];
    expected_shape.extend_from_slice(space.shape());
    let expected = || {
        format!(
            "actions must be {} of shape {:?} ({num_envs} envs, each {})",
            space.dtype().name(),
            expected_shape,
            space.describe()
        )
    };
    if dtype != space.dtype() || shape != expected_shape.as_slice() {
        return Err(CoreError::InvalidActions(format!("{}; got {} of shape {:?}", expected(), dtype.name(), shape)));
    }
    let count: usize = expected_shape.iter().product();
    if data.len() != count * dtype.size_of() {
        return Err(CoreError::InvalidActions(format!(
            "{}; the tensor's shape says {count} elements but it holds {} bytes",
            expected(),
            data.len()
        )));
    }
    let per_env = space.num_elements().max(1);
    match space {
        Space::Box { low, high, .. } => {
            for (index, chunk) in data.chunks_exact(dtype.size_of()).enumerate() {
                let value = read_number(dtype, chunk);
                let element = index % per_env;
                let bound = |bounds: &Vec<f64>, fallback: f64| {
                    bounds.get(if bounds.len() == 1 { 0 } else { element }).copied().unwrap_or(fallback)
                };
                let (lo, hi) = (bound(low, f64::NEG_INFINITY), bound(high, f64::INFINITY));
                if value.is_nan() || value < lo || value > hi {
                    return Err(CoreError::InvalidActions(format!(
                        "action {value} of env {}, element {element} is outside [{lo}, {hi}]; {}",
                        index / per_env,
                        expected()
                    )));
                }
            }
        }
        Space::Discrete { n } => {
            for (env, chunk) in data.chunks_exact(8).enumerate() {
                let value = i64::from_le_bytes(chunk.try_into().expect("8 bytes"));
                if value < 0 || value >= *n {
                    return Err(CoreError::InvalidActions(format!(
                        "action {value} of env {env} is outside [0, {n}); {}",
                        expected()
                    )));
                }
            }
        }
    }
    Ok(())
}

fn read_number(dtype: DType, bytes: &[u8]) -> f64 {
    match dtype {
        DType::Float32 => f32::from_le_bytes(bytes.try_into().expect("4 bytes")) as f64,
        DType::Float64 => f64::from_le_bytes(bytes.try_into().expect("8 bytes")),
        DType::Int32 => i32::from_le_bytes(bytes.try_into().expect("4 bytes")) as f64,
        DType::Int64 => i64::from_le_bytes(bytes.try_into().expect("8 bytes")) as f64,
        DType::Uint8 | DType::Bool => bytes[0] as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bytes_f32(values: &[f32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    fn unit_box(dims: usize) -> Space {
        Space::Box { dtype: DType::Float32, shape: vec![dims], low: vec![-1.0], high: vec![1.0] }
    }

    #[test]
    fn good_actions_pass() {
        let data = bytes_f32(&[0.5, -0.5, 1.0, -1.0]);
        validate_actions(&unit_box(2), 2, DType::Float32, &[2, 2], &data).unwrap();
    }

    #[test]
    fn wrong_shape_dtype_bounds_and_nan_are_rejected_with_the_spec() {
        let space = unit_box(2);
        let data = bytes_f32(&[0.5, -0.5, 1.0, -1.0]);
        let shape_error = validate_actions(&space, 2, DType::Float32, &[4], &data).unwrap_err().to_string();
        assert!(shape_error.contains("float32 of shape [2, 2]"), "{shape_error}");
        let dtype_error = validate_actions(&space, 2, DType::Float64, &[2, 2], &data).unwrap_err().to_string();
        assert!(dtype_error.contains("got float64"), "{dtype_error}");
        let too_big = bytes_f32(&[0.5, 1.5, 0.0, 0.0]);
        let bound_error = validate_actions(&space, 2, DType::Float32, &[2, 2], &too_big).unwrap_err().to_string();
        assert!(bound_error.contains("env 0, element 1 is outside [-1, 1]"), "{bound_error}");
        let nan = bytes_f32(&[0.0, 0.0, f32::NAN, 0.0]);
        let nan_error = validate_actions(&space, 2, DType::Float32, &[2, 2], &nan).unwrap_err().to_string();
        assert!(nan_error.contains("NaN of env 1"), "{nan_error}");
        let short = validate_actions(&space, 2, DType::Float32, &[2, 2], &data[..12]).unwrap_err().to_string();
        assert!(short.contains("holds 12 bytes"), "{short}");
    }

    #[test]
    fn discrete_actions_must_be_in_range() {
        let space = Space::Discrete { n: 15 };
        let ok: Vec<u8> = [0i64, 14].iter().flat_map(|v| v.to_le_bytes()).collect();
        validate_actions(&space, 2, DType::Int64, &[2], &ok).unwrap();
        let bad: Vec<u8> = [3i64, 15].iter().flat_map(|v| v.to_le_bytes()).collect();
        let error = validate_actions(&space, 2, DType::Int64, &[2], &bad).unwrap_err().to_string();
        assert!(error.contains("action 15 of env 1 is outside [0, 15)"), "{error}");
    }

    #[test]
    fn stacks_shift_oldest_out() {
        let mut stack = vec![1, 1, 2, 2, 3, 3];
        push_frame(&mut stack, &[4, 4]);
        assert_eq!(stack, vec![2, 2, 3, 3, 4, 4]);
        let mut single = vec![7, 7];
        push_frame(&mut single, &[8, 8]);
        assert_eq!(single, vec![8, 8]);
    }

    #[test]
    fn seeds_must_fit_in_32_bits() {
        assert!(check_seed(0, 16).is_ok());
        assert!(check_seed(MAX_SEED, 1).is_err());
    }
}
