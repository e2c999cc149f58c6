//! A session: a vector of environments of one id, spread over worker processes, whose observations are
//! frame-stacked here in the server (frames travel from workers once).
//!
//! Autoreset is "same-step" (EnvPool, gymnasium's `AutoresetMode.SAME_STEP`): the step that ends an
//! episode returns the first observation of the next one, and the last observation of the ended
//! episode separately, as `final_obs`.

use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};

use radserve_augment::{Augmentation, Draws, FrameShape, ImagePlan, Pipeline};
use radserve_replay::{RecordedStep, ReplayBuffer};

use crate::catalog::{EnvId, Options};
use crate::error::SimError;
use crate::pool::{await_generation, await_reply, WorkerFault, WorkerHandle, WorkerPool};
use crate::protocol::{EnvSpec, GroupConfig, Request, Response};
use crate::shm::{FrameLayout, SharedFrames};
use crate::space::{DType, Space};

/// Largest seed + num_envs: dm_control and ProcGen seeds are 32-bit signed integers.
pub const MAX_SEED: u64 = i32::MAX as u64;

static NEXT_GROUP: AtomicU64 = AtomicU64::new(1);

/// The counters of a session that change as it acts, readable without its lock.
#[derive(Debug, Default)]
pub struct SessionStats {
    pub seed: AtomicU64,
    pub total_env_steps: AtomicU64,
    pub episodes_completed: AtomicU64,
}

pub struct SessionConfig {
    pub env: EnvId,
    pub num_envs: usize,
    pub seed: u64,
    /// Resolved options (defaults included).
    pub options: Options,
    pub frame_stack: usize,
}

struct Group {
    worker: WorkerHandle,
    id: u64,
    envs: Range<usize>,
    seeds: Vec<u64>,
    frames: SharedFrames,
    /// The worker process generation whose envs this session's stacks follow: a step is refused by a
    /// newer process (which rebuilt the group unreset), and the episodes end instead.
    generation: u64,
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
}

pub struct Session {
    pub config: SessionConfig,
    /// One frame of one environment.
    pub frame_spec: EnvSpec,
    /// One (stacked) observation of one environment.
    pub observation_space: Space,
    groups: Vec<Group>,
    layout: FrameLayout,
    /// The stacked observation of every env, oldest frame first.
    stacks: Vec<u8>,
    episode_returns: Vec<f64>,
    episode_lengths: Vec<u64>,
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
}

impl Session {
    /// Builds the environments on the least loaded workers, one contiguous group of envs per worker.
    pub async fn create(pool: &WorkerPool, config: SessionConfig) -> Result<Session, SimError> {
        let workers = pool.least_loaded(config.num_envs);
        let ranges = split_evenly(config.num_envs, workers.len());
        let mut worker_options = config.options.clone();
        worker_options.remove(crate::catalog::FRAME_STACK);

        let mut pending = Vec::new();
        for (worker, envs) in workers.iter().zip(&ranges) {
            let group = NEXT_GROUP.fetch_add(1, Ordering::Relaxed);
            let seeds: Vec<u64> = envs.clone().map(|i| config.seed + i as u64).collect();
            let request = Request::CreateGroup(GroupConfig {
                group,
                family: config.env.family,
                name: config.env.name.clone(),
                options: worker_options.clone(),
                seeds: seeds.clone(),
            });
            pending.push((worker.clone(), group, envs.clone(), seeds, worker.submit(request).await));
        }
        let mut created = Vec::new();
        let mut failure = None;
        let mut spec = None;
        for (worker, group, envs, seeds, receiver) in pending {
            match await_generation(receiver).await {
                Ok((Response::Created(group_spec), generation)) => {
                    spec.get_or_insert(group_spec);
                    created.push((worker, group, envs, seeds, generation));
                }
                Ok((Response::Failed(message), _)) => {
                    failure.get_or_insert(SimError::CreateFailed { env_id: config.env.full(), message });
                }
                Ok((other, _)) => {
                    failure.get_or_insert(unexpected(Ok(other)));
                }
                Err(fault) => {
                    failure.get_or_insert(unexpected(Err(fault)));
                }
            }
        }
        if let Some(error) = failure {
            for (worker, group, ..) in created {
                let _ = worker.call(Request::CloseGroup { group }).await;
            }
            return Err(error);
        }
        let frame_spec = spec.expect("at least one group");
        let layout = FrameLayout { frame_bytes: frame_spec.observation.num_bytes() };

        let mut groups = Vec::new();
        for (worker, id, envs, seeds, generation) in &created {
            match SharedFrames::create(layout.segment_len(envs.len())) {
                Ok(frames) => groups.push(Group {
                    worker: worker.clone(),
                    id: *id,
                    envs: envs.clone(),
                    seeds: seeds.clone(),
                    frames,
                    generation: *generation,
                }),
                Err(err) => {
                    for (worker, group, ..) in &created {
                        let _ = worker.call(Request::CloseGroup { group: *group }).await;
                    }
                    return Err(resource_error("allocating the session's shared frames", &err));
                }
            }
        }
        let config_seed = config.seed;
        let mut session = Session {
            observation_space: frame_spec.observation.stacked(config.frame_stack),
            stacks: vec![0; config.num_envs * config.frame_stack * layout.frame_bytes],
            episode_returns: vec![0.0; config.num_envs],
            episode_lengths: vec![0; config.num_envs],
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
        };
        let attached = session.attach_all().await;
        for group in &session.groups {
            group.worker.add_hosted_envs(group.envs.len());
        }
        if let Err(error) = attached {
            session.close().await;
            return Err(error);
        }
        Ok(session)
    }

    async fn attach_all(&mut self) -> Result<(), SimError> {
        let mut pending = Vec::new();
        for group in &self.groups {
            let request =
                Request::Attach { group: group.id, shm_path: group.frames.child_path(), shm_len: group.frames.len() };
            pending.push(group.worker.submit(request).await);
        }
        for receiver in pending {
            match await_reply(receiver).await {
                Ok(Response::Attached) => {}
                other => return Err(unexpected(other)),
            }
        }
        Ok(())
    }

    pub fn num_envs(&self) -> usize {
        self.config.num_envs
    }

    /// Return observations through `view` (a centre crop or centre translate, RAD's evaluation
    /// views), so that a policy trained on augmented crops acts on the matching view.
    pub fn set_view(&mut self, text: &str) -> Result<(), SimError> {
        let invalid = |message: String| SimError::InvalidArgument(format!("observation_view {text:?}: {message}"));
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

    /// Record each env of group `index` starting an episode at its current frame, before the
    /// Step call `step_index`.
    fn record_first_frames(&self, index: usize, step_index: u64) {
        let Some(replay) = &self.replay else { return };
        let mut replay = replay.write().expect("replay lock");
        let group = &self.groups[index];
        for (local, env) in group.envs.clone().enumerate() {
            replay.abandon_episode(env);
            replay.record_first_frame(env, &group.frames.as_slice()[self.layout.frame(local)], step_index);
        }
    }

    fn stack_bytes(&self) -> usize {
        self.config.frame_stack * self.layout.frame_bytes
    }

    /// Resets every environment (re-seeding env i with seed + i when a seed is given) and returns the
    /// stacked observations: the first frame repeated `frame_stack` times.
    pub async fn reset(&mut self, seed: Option<u64>) -> Result<Vec<u8>, SimError> {
        if let Some(seed) = seed {
            check_seed(seed, self.num_envs())?;
            self.config.seed = seed;
            self.stats.seed.store(seed, Ordering::Relaxed);
            for group in &mut self.groups {
                group.seeds = group.envs.clone().map(|i| seed + i as u64).collect();
            }
        }
        let mut pending = Vec::new();
        for group in &self.groups {
            let seeds = seed.map(|_| group.seeds.clone());
            pending.push(group.worker.submit(Request::Reset { group: group.id, seeds }).await);
        }
        for (index, receiver) in pending.into_iter().enumerate() {
            match await_generation(receiver).await {
                Ok((Response::Reset, generation)) => self.groups[index].generation = generation,
                // The worker was replaced and the group rebuilt from its seeds: reset that one again.
                Err(WorkerFault::Crashed(_)) => self.reset_group(index).await?,
                Ok((other, _)) => return Err(unexpected(Ok(other))),
                Err(fault) => return Err(unexpected(Err(fault))),
            }
        }
        for index in 0..self.groups.len() {
            self.fill_stacks_from_current(index);
            self.record_first_frames(index, self.step_calls);
        }
        self.episode_returns.iter_mut().for_each(|value| *value = 0.0);
        self.episode_lengths.iter_mut().for_each(|value| *value = 0);
        self.needs_reset = false;
        Ok(self.viewed(&self.stacks))
    }

    async fn reset_group(&mut self, index: usize) -> Result<(), SimError> {
        let group = &self.groups[index];
        let request = Request::Reset { group: group.id, seeds: Some(group.seeds.clone()) };
        match group.worker.call_generation(request).await {
            Ok((Response::Reset, generation)) => {
                self.groups[index].generation = generation;
                Ok(())
            }
            Ok((other, _)) => Err(unexpected(Ok(other))),
            Err(fault) => Err(unexpected(Err(fault))),
        }
    }

    /// Sets each stack of a group to its env's current frame repeated (the stacking at reset).
    fn fill_stacks_from_current(&mut self, index: usize) {
        let stack_bytes = self.stack_bytes();
        let group = &self.groups[index];
        for (local, env) in group.envs.clone().enumerate() {
            let frame = &group.frames.as_slice()[self.layout.frame(local)];
            for slot in self.stacks[env * stack_bytes..(env + 1) * stack_bytes].chunks_exact_mut(frame.len()) {
                slot.copy_from_slice(frame);
            }
        }
    }

    /// Steps every environment with `actions` ([num_envs, *action shape] of the action dtype).
    pub async fn step(&mut self, dtype: DType, shape: &[usize], actions: &[u8]) -> Result<StepOutcome, SimError> {
        if self.needs_reset {
            return Err(SimError::FailedPrecondition("call Reset on this session before Step".into()));
        }
        validate_actions(&self.frame_spec.action, self.num_envs(), dtype, shape, actions)?;
        let action_bytes = self.frame_spec.action.num_bytes();
        let mut pending = Vec::new();
        for group in &self.groups {
            let slice = actions[group.envs.start * action_bytes..group.envs.end * action_bytes].to_vec();
            // Refused by a newer process of the worker: the group was rebuilt there (another
            // session's step crashed it, or it was stuck) and its episodes end here instead.
            pending.push(group.worker.submit_in(Request::Step { group: group.id, actions: slice }, group.generation).await);
        }
        let num_envs = self.num_envs();
        let mut outcome = StepOutcome {
            rewards: vec![0.0; num_envs],
            terminated: vec![false; num_envs],
            truncated: vec![false; num_envs],
            ..StepOutcome::default()
        };
        for (index, receiver) in pending.into_iter().enumerate() {
            let result = match await_reply(receiver).await {
                // A worker's answer sized for another group (a bug, or a broken worker) ends the
                // step cleanly instead of indexing past it below.
                Ok(Response::Stepped(result)) if result.fits(self.groups[index].envs.len()) => result,
                Ok(Response::Stepped(result)) => {
                    self.needs_reset = true;
                    return Err(SimError::Simulator(format!(
                        "worker answered a step of {} envs with {} rewards, {} terminated and {} truncated flags",
                        self.groups[index].envs.len(),
                        result.rewards.len(),
                        result.terminated.len(),
                        result.truncated.len()
                    )));
                }
                Err(WorkerFault::Crashed(message)) => {
                    self.recover_crashed_group(index, &message, &mut outcome).await?;
                    continue;
                }
                other => {
                    self.needs_reset = true;
                    return Err(unexpected(other));
                }
            };
            let group_envs = self.groups[index].envs.clone();
            if let Some(replay) = &self.replay {
                // Recorded before the stacks move on; sync, so no lock is held across an await.
                let mut replay = replay.write().expect("replay lock");
                let group = &self.groups[index];
                for (local, env) in group_envs.clone().enumerate() {
                    let ended = result.terminated[local] || result.truncated[local];
                    let next = if ended { self.layout.final_frame(local) } else { self.layout.frame(local) };
                    replay.record_step(
                        env,
                        &RecordedStep {
                            action: &actions[env * action_bytes..(env + 1) * action_bytes],
                            reward: result.rewards[local],
                            terminated: result.terminated[local],
                            truncated: result.truncated[local],
                            next_frame: &group.frames.as_slice()[next],
                            step_index: self.step_calls,
                        },
                    );
                    if ended {
                        let first = &group.frames.as_slice()[self.layout.frame(local)];
                        replay.record_first_frame(env, first, self.step_calls + 1);
                    }
                }
            }
            for (local, env) in group_envs.enumerate() {
                let (reward, terminated, truncated) =
                    (result.rewards[local], result.terminated[local], result.truncated[local]);
                outcome.rewards[env] = reward;
                outcome.terminated[env] = terminated;
                outcome.truncated[env] = truncated;
                self.episode_returns[env] += reward;
                self.episode_lengths[env] += 1;
                let group = &self.groups[index];
                let frame = &group.frames.as_slice()[self.layout.frame(local)];
                let stack = &mut self.stacks[env * self.config.frame_stack * self.layout.frame_bytes..]
                    [..self.config.frame_stack * self.layout.frame_bytes];
                if terminated || truncated {
                    let final_frame = &group.frames.as_slice()[self.layout.final_frame(local)];
                    push_frame(stack, final_frame);
                    outcome.final_obs.extend_from_slice(stack);
                    for slot in stack.chunks_exact_mut(frame.len()) {
                        slot.copy_from_slice(frame);
                    }
                    let error = result.errors.iter().find(|(j, _)| *j as usize == local).map(|(_, m)| m.clone());
                    outcome.episodes.push(self.end_episode(env, terminated, truncated, error));
                } else {
                    push_frame(stack, frame);
                }
            }
        }
        self.total_env_steps += num_envs as u64;
        self.stats.total_env_steps.store(self.total_env_steps, Ordering::Relaxed);
        self.stats.episodes_completed.store(self.episodes_completed, Ordering::Relaxed);
        self.step_calls += 1;
        outcome.obs = self.viewed(&self.stacks);
        outcome.final_obs = self.viewed(&outcome.final_obs);
        Ok(outcome)
    }

    /// After a worker died mid-step: its envs' episodes end as truncated with the error, their last
    /// observation is the stack before the step, and they start again from a reset.
    async fn recover_crashed_group(
        &mut self,
        index: usize,
        message: &str,
        outcome: &mut StepOutcome,
    ) -> Result<(), SimError> {
        if let Err(error) = self.reset_group(index).await {
            self.needs_reset = true;
            return Err(error);
        }
        let stack_bytes = self.stack_bytes();
        for env in self.groups[index].envs.clone() {
            outcome.final_obs.extend_from_slice(&self.stacks[env * stack_bytes..(env + 1) * stack_bytes]);
            outcome.truncated[env] = true;
            self.episode_lengths[env] += 1;
            outcome.episodes.push(self.end_episode(env, false, true, Some(message.to_string())));
        }
        self.fill_stacks_from_current(index);
        // The crashed step has no next frame to record; the episodes restart from the new frames.
        self.record_first_frames(index, self.step_calls + 1);
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

    /// Releases the environments in their workers.
    pub async fn close(&mut self) {
        for group in self.groups.drain(..) {
            let _ = group.worker.call(Request::CloseGroup { group: group.id }).await;
            group.worker.remove_hosted_envs(group.envs.len());
        }
    }
}

/// Drops the oldest frame of a stack and appends `frame`.
fn push_frame(stack: &mut [u8], frame: &[u8]) {
    stack.copy_within(frame.len().., 0);
    let tail = stack.len() - frame.len();
    stack[tail..].copy_from_slice(frame);
}

/// `total` items over `parts` contiguous ranges whose sizes differ by at most one.
fn split_evenly(total: usize, parts: usize) -> Vec<Range<usize>> {
    let parts = parts.clamp(1, total.max(1));
    let (base, extra) = (total / parts, total % parts);
    let mut start = 0;
    (0..parts)
        .map(|part| {
            let len = base + usize::from(part < extra);
            let range = start..start + len;
            start += len;
            range
        })
        .collect()
}

pub fn check_seed(seed: u64, num_envs: usize) -> Result<(), SimError> {
    if seed.saturating_add(num_envs as u64) > MAX_SEED {
        return Err(SimError::InvalidArgument(format!(
            "seed + num_envs must be at most {MAX_SEED} (simulators take 32-bit seeds); got seed {seed} with {num_envs} envs"
        )));
    }
    Ok(())
}

/// An allocation that failed: out of file descriptors or memory is a limit of this server
/// (RESOURCE_EXHAUSTED, worth retrying elsewhere or later), anything else a server failure.
pub fn resource_error(what: &str, error: &std::io::Error) -> SimError {
    match error.raw_os_error() {
        Some(libc::EMFILE | libc::ENFILE) => {
            SimError::LimitExceeded(format!("{what}: the server is out of file descriptors ({error}); try again later"))
        }
        Some(libc::ENOMEM | libc::ENOSPC) => SimError::LimitExceeded(format!("{what}: the server is out of memory ({error})")),
        _ => SimError::Simulator(format!("{what}: {error}")),
    }
}

fn unexpected(outcome: Result<Response, WorkerFault>) -> SimError {
    match outcome {
        Ok(Response::Failed(message)) => SimError::Simulator(message),
        Ok(other) => SimError::Simulator(format!("unexpected worker response {other:?}")),
        Err(WorkerFault::Crashed(message)) => SimError::Simulator(message),
        Err(WorkerFault::Unavailable(message)) => SimError::WorkersUnavailable(message),
    }
}

/// Checks a batch of actions against the action space: dtype, shape, finiteness and bounds.
pub fn validate_actions(
    space: &Space,
    num_envs: usize,
    dtype: DType,
    shape: &[usize],
    data: &[u8],
) -> Result<(), SimError> {
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
        return Err(SimError::InvalidArgument(format!("{}; got {} of shape {:?}", expected(), dtype.name(), shape)));
    }
    let count: usize = expected_shape.iter().product();
    if data.len() != count * dtype.size_of() {
        return Err(SimError::InvalidArgument(format!(
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
                    return Err(SimError::InvalidArgument(format!(
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
                    return Err(SimError::InvalidArgument(format!(
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
    fn envs_split_evenly_over_workers() {
        assert_eq!(split_evenly(5, 2), vec![0..3, 3..5]);
        assert_eq!(split_evenly(1, 4), vec![0..1]);
        assert_eq!(split_evenly(4, 4), vec![0..1, 1..2, 2..3, 3..4]);
    }

    #[test]
    fn seeds_must_fit_in_32_bits() {
        assert!(check_seed(0, 16).is_ok());
        assert!(check_seed(MAX_SEED, 1).is_err());
    }
}
