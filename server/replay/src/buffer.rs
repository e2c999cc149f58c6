//! A replay buffer that stores every frame once.
//!
//! Each environment owns a ring of slots. A slot holds one frame and, unless the frame is the first
//! of an episode, the transition that led into it (action, reward, terminated, truncated). The
//! transition into slot `i` has the observation stack ending at frame `i - 1` and the next
//! observation stack ending at frame `i`; a stack never reaches before its episode's first frame,
//! which pads it instead, exactly as the session's stacking does at reset. RAD's reference buffer
//! keeps obs and next_obs stacks separately, `2k` frames per transition; this one keeps slightly
//! more than one (one extra frame per episode, plus `k` per environment for the oldest stacks).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use rand::Rng;

use crate::error::{ReplayError, Result};
use crate::priority::Priorities;
use crate::rate_limiter::{Activity, Occupancy};

/// Whether a buffer serves uniform replay or the last rollout.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum BufferKind {
    /// Off-policy replay: uniform sampling with replacement over the last `capacity` transitions.
    #[default]
    Replay,
    /// On-policy rollouts: the last `steps` steps of every environment, served in permuted epochs.
    Rollout { steps: usize },
}

/// What a replay buffer stores, fixed at creation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReplayLayout {
    pub kind: BufferKind,
    /// Transitions kept, over all environments (the oldest are overwritten). For a rollout,
    /// `steps * num_envs`.
    pub capacity: usize,
    pub num_envs: usize,
    /// Frames per observation stack.
    pub frame_stack: usize,
    /// Bytes of one frame (uint8 pixels, or float32 state bytes).
    pub frame_bytes: usize,
    /// Bytes of one environment's action.
    pub action_bytes: usize,
}

impl ReplayLayout {
    /// Slots in each environment's ring: its share of the capacity, plus the `frame_stack` frames
    /// the oldest transition's observation reaches back to.
    ///
    /// Sizes here come from request fields, so every product saturates instead of wrapping: a size
    /// that does not fit in memory stays too large for [`ReplayLayout::validate`] and the budget.
    pub fn slots_per_env(&self) -> usize {
        match self.kind {
            BufferKind::Replay => self.capacity.div_ceil(self.num_envs.max(1)).saturating_add(self.frame_stack),
            // Every step may end an episode and add a first frame: room for two frames a step.
            BufferKind::Rollout { steps } => steps.saturating_mul(2).saturating_add(self.frame_stack),
        }
    }

    /// A rollout buffer for the last `steps` steps of `num_envs` environments.
    pub fn rollout(steps: usize, num_envs: usize, frame_stack: usize, frame_bytes: usize, action_bytes: usize) -> Self {
        let capacity = steps.saturating_mul(num_envs);
        Self { kind: BufferKind::Rollout { steps }, capacity, num_envs, frame_stack, frame_bytes, action_bytes }
    }

    /// Bytes of one slot: the frame and its transition's metadata.
    pub fn slot_bytes(&self) -> usize {
        self.frame_bytes.saturating_add(self.action_bytes).saturating_add(SLOT_METADATA_BYTES)
    }

    /// Bytes of one slot's record in a snapshot: the frame, the action and the metadata a snapshot
    /// keeps (the actor's columns are not kept: restored transitions have `NO_POLICY`).
    pub(crate) fn snapshot_record_bytes(&self) -> usize {
        self.frame_bytes.saturating_add(self.action_bytes).saturating_add(SNAPSHOT_METADATA_BYTES)
    }

    /// Slots over all environments.
    fn total_slots(&self) -> usize {
        self.num_envs.saturating_mul(self.slots_per_env())
    }

    /// Everything the buffer allocates, computed before allocating it (saturating: `usize::MAX`
    /// means "more than can be addressed").
    pub fn memory_bytes(&self) -> usize {
        self.total_slots().saturating_mul(self.slot_bytes())
    }

    /// Frames stored per transition when full (frames over transitions, before episode starts).
    pub fn frames_per_transition(&self) -> f64 {
        self.total_slots() as f64 / self.capacity.max(1) as f64
    }

    pub fn validate(&self) -> Result<()> {
        let invalid = |message: String| Err(ReplayError::InvalidArgument(message));
        if self.capacity == 0 {
            return invalid("replay capacity must be at least 1 transition".into());
        }
        if self.num_envs == 0 || self.frame_stack == 0 || self.frame_bytes == 0 {
            return invalid(format!("replay layout has an empty dimension: {self:?}"));
        }
        if self.capacity < self.num_envs {
            return invalid(format!(
                "replay capacity {} is below the number of environments {}; each needs room for one transition",
                self.capacity, self.num_envs
            ));
        }
        check_capacity(self.capacity)?;
        // Checked again without saturation: every allocation `new` makes must be addressable.
        let addressable = self
            .num_envs
            .checked_mul(self.slots_per_env())
            .and_then(|slots| slots.checked_mul(self.slot_bytes()))
            .is_some_and(|bytes| bytes <= isize::MAX as usize);
        if !addressable {
            return invalid(format!(
                "a replay buffer of {} transitions for {} envs of {} bytes per frame cannot be addressed",
                self.capacity, self.num_envs, self.frame_bytes
            ));
        }
        Ok(())
    }
}

/// The most transitions one buffer may hold (2^40: far above any memory budget at one byte a frame,
/// far below where slot arithmetic could overflow).
pub const MAX_CAPACITY: usize = 1 << 40;

/// The least a stored transition takes, whatever its frames and actions: its slot's bookkeeping.
pub const MIN_BYTES_PER_TRANSITION: usize = SLOT_METADATA_BYTES;

/// Refuses a capacity above [`MAX_CAPACITY`] (checked by `ReplayLayout::validate`, and by callers
/// before they know the rest of the layout).
pub fn check_capacity(capacity: usize) -> Result<()> {
    if capacity > MAX_CAPACITY {
        return Err(ReplayError::InvalidArgument(format!(
            "replay capacity {capacity} is above the most a buffer can hold, {MAX_CAPACITY} transitions"
        )));
    }
    Ok(())
}

/// reward (f32), flags (u8), episode start (u64), step index (u64), and what a server-side actor
/// recorded: policy version (i32), log-probability and value (f32).
pub(crate) const SLOT_METADATA_BYTES: usize = 4 + 1 + 8 + 8 + 4 + 4 + 4;

/// The part of a slot's metadata a snapshot keeps: reward, flags, episode start, step index.
pub(crate) const SNAPSHOT_METADATA_BYTES: usize = 4 + 1 + 8 + 8;

/// The policy version of a transition no server-side policy acted in (a client's Step, the
/// actor's random warm-up steps, a transition restored from a snapshot).
pub const NO_POLICY: i32 = -1;

pub(crate) const FIRST_OF_EPISODE: u8 = 1;
pub(crate) const TERMINATED: u8 = 2;
pub(crate) const TRUNCATED: u8 = 4;

/// Where a sampled transition lives.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TransitionRef {
    pub env: usize,
    /// The absolute index (frames written to this env before it) of the transition's next frame.
    pub frame: u64,
}

/// The low bits of a transition's key that hold its frame; the env is above them (see
/// [`TransitionRef::key`]).
pub const KEY_FRAME_BITS: u32 = 40;

impl TransitionRef {
    /// The key a batch carries for this transition, by which `UpdatePriorities` names it: the env
    /// in the high 24 bits, the frame in the low 40 (2^40 frames per env: 35 years at 1000 steps
    /// per second).
    pub fn key(self) -> u64 {
        ((self.env as u64) << KEY_FRAME_BITS) | self.frame
    }

    pub fn from_key(key: u64) -> TransitionRef {
        TransitionRef { env: (key >> KEY_FRAME_BITS) as usize, frame: key & ((1 << KEY_FRAME_BITS) - 1) }
    }
}

/// The most steps one n-step return may sum (DrQ-v2 and Rainbow use 3, R2D2 5, Ape-X 3).
pub const MAX_N_STEP: usize = 64;

/// How a sampled transition's return is summed: up to `n_step` rewards from its step on, each
/// discounted by `discount` once more than the one before.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Returns {
    pub n_step: usize,
    pub discount: f64,
}

impl Returns {
    /// Checks the bounds: `n_step` in `1..=MAX_N_STEP`, `discount` in [0, 1].
    pub fn new(n_step: usize, discount: f64) -> Result<Returns> {
        if !(1..=MAX_N_STEP).contains(&n_step) {
            return Err(ReplayError::InvalidArgument(format!("n_step must be between 1 and {MAX_N_STEP}, got {n_step}")));
        }
        if !(0.0..=1.0).contains(&discount) {
            return Err(ReplayError::InvalidArgument(format!("discount must be in [0, 1], got {discount}")));
        }
        Ok(Returns { n_step, discount })
    }
}

/// A transition's n-step window: the steps from it to the first that ended its episode, at most
/// `n_step` of them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Window {
    /// Rewards summed (1..=n_step).
    pub steps: usize,
    /// `sum_{k < steps} discount^k * reward_{t+k}`.
    pub reward: f64,
    /// The bootstrap's factor: `discount^steps`, or 0 when the episode terminated in the window.
    pub discount: f64,
    pub terminated: bool,
    pub truncated: bool,
    /// The frame the next observation's stack ends at: the one after the last summed step.
    pub last_frame: u64,
}

/// Where draws come from: (oldest sampleable frame, frames written) per env.
pub(crate) struct Candidates {
    ranges: Vec<(u64, u64)>,
    pub(crate) total: u64,
}

impl Candidates {
    /// One (env, frame) drawn uniformly among the candidates (`total` > 0).
    pub(crate) fn pick(&self, rng: &mut impl Rng) -> TransitionRef {
        let span = |env: usize| self.ranges[env].1.saturating_sub(self.ranges[env].0);
        let mut pick = rng.random_range(0..self.total);
        let mut env = 0;
        while pick >= span(env) {
            pick -= span(env);
            env += 1;
        }
        TransitionRef { env, frame: self.ranges[env].0 + pick }
    }
}

/// Counters for the statistics RPC and the rate limiter.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ReplayCounters {
    /// Transitions recorded since creation.
    pub inserts: u64,
    /// Transitions handed out by samplers since creation.
    pub samples: u64,
    /// Minibatches handed out by samplers since creation.
    pub batches: u64,
}

/// Batches over the last few seconds, for the rate the statistics show.
#[derive(Debug, Default)]
struct RecentBatches {
    times: std::collections::VecDeque<Instant>,
    first: Option<Instant>,
}

impl RecentBatches {
    const WINDOW: Duration = Duration::from_secs(5);

    fn record(&mut self, now: Instant) {
        self.first.get_or_insert(now);
        self.times.push_back(now);
        while self.times.front().is_some_and(|&time| now.duration_since(time) > Self::WINDOW) {
            self.times.pop_front();
        }
    }

    /// Batches per second over the last 5 s (or since the first batch, counted as at least 1 s).
    fn per_second(&self, now: Instant) -> f64 {
        let Some(first) = self.first else { return 0.0 };
        let recent = self.times.iter().filter(|&&time| now.duration_since(time) <= Self::WINDOW).count();
        let span = now.duration_since(first).clamp(Duration::from_secs(1), Self::WINDOW);
        recent as f64 / span.as_secs_f64()
    }
}

pub struct ReplayBuffer {
    pub(crate) layout: ReplayLayout,
    pub(crate) slots: usize,
    pub(crate) frames: Vec<u8>,
    pub(crate) actions: Vec<u8>,
    pub(crate) rewards: Vec<f32>,
    pub(crate) flags: Vec<u8>,
    pub(crate) episode_starts: Vec<u64>,
    pub(crate) step_indices: Vec<u64>,
    /// Per slot: the version of the server-side policy that acted (`NO_POLICY`: none), the head's
    /// log-probability of the action and the model's value (0 where none).
    pub(crate) policy_versions: Vec<i32>,
    pub(crate) log_probs: Vec<f32>,
    pub(crate) values: Vec<f32>,
    /// Per env: frames written so far (the absolute index of the next one).
    pub(crate) written: Vec<u64>,
    /// Per env: the first frame its slots hold for certain. 0, except after a restore whose snapshot
    /// lost older frames (the snapshot writer was lapped, or the snapshot was compacted): frames below
    /// it are stale, so no stack may reach below it.
    pub(crate) floors: Vec<u64>,
    /// Per env: whether an episode is in progress (a first frame was recorded and it has not ended).
    pub(crate) in_episode: Vec<bool>,
    /// Per env: the episodes' first frames among its sampleable frames (`oldest_sampleable..written`),
    /// kept as frames are written so that `len` is O(envs), not a scan of the buffer per batch.
    pub(crate) first_frames: Vec<u64>,
    /// One past the largest step index recorded.
    pub(crate) steps_recorded: u64,
    pub(crate) counters: ReplayCounters,
    recent_batches: RecentBatches,
    /// Producers (sample streams) running on this buffer.
    active_producers: Arc<AtomicUsize>,
    /// Woken by each insert and each sampled batch: the waiters on the rate limiter.
    activity: Arc<Activity>,
    /// Each sampleable transition's priority, from the first prioritized stream on (None before:
    /// uniform streams need none).
    pub(crate) priorities: Option<Priorities>,
}

/// One admitted sample stream of a buffer; dropping it frees its place (see
/// [`ReplayBuffer::admit_producer`]).
#[derive(Debug)]
pub struct ProducerPermit(Arc<AtomicUsize>);

impl Drop for ProducerPermit {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// One env's outcome of a step, as the session records it.
#[derive(Clone, Copy, Debug)]
pub struct RecordedStep<'a> {
    pub action: &'a [u8],
    pub reward: f64,
    pub terminated: bool,
    pub truncated: bool,
    /// The frame the action led to: for an episode that ended, its last frame.
    pub next_frame: &'a [u8],
    /// The session's step counter for this step (the index of the Step call).
    pub step_index: u64,
    /// What a server-side actor acted with: the policy's version, the action's log-probability and
    /// the model's value (None: no policy acted).
    pub acted: Option<ActedBy>,
}

/// The policy behind a recorded action.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ActedBy {
    pub version: i32,
    pub log_prob: f32,
    pub value: f32,
}

impl ReplayBuffer {
    /// Allocate the buffer (zero pages: the memory is committed as it fills).
    pub fn new(layout: ReplayLayout) -> Result<Self> {
        layout.validate()?;
        let slots = layout.slots_per_env();
        let total = layout.num_envs * slots;
        Ok(Self {
            layout,
            slots,
            frames: vec![0; total * layout.frame_bytes],
            actions: vec![0; total * layout.action_bytes],
            rewards: vec![0.0; total],
            flags: vec![0; total],
            episode_starts: vec![0; total],
            step_indices: vec![0; total],
            policy_versions: vec![NO_POLICY; total],
            log_probs: vec![0.0; total],
            values: vec![0.0; total],
            written: vec![0; layout.num_envs],
            floors: vec![0; layout.num_envs],
            in_episode: vec![false; layout.num_envs],
            first_frames: vec![0; layout.num_envs],
            steps_recorded: 0,
            counters: ReplayCounters::default(),
            recent_batches: RecentBatches::default(),
            active_producers: Arc::default(),
            activity: Arc::default(),
            priorities: None,
        })
    }

    pub fn layout(&self) -> &ReplayLayout {
        &self.layout
    }

    /// Frames recorded so far, over all envs (first frames included).
    pub fn frames_written(&self) -> u64 {
        self.written.iter().sum()
    }

    /// One past the largest step index recorded (restored with the buffer).
    pub fn steps_recorded(&self) -> u64 {
        self.steps_recorded
    }

    pub fn counters(&self) -> ReplayCounters {
        self.counters
    }

    /// What the rate limiter reads: the counters and the transitions held now.
    pub fn occupancy(&self) -> Occupancy {
        Occupancy::of(self.counters, self.len())
    }

    /// Signalled by each insert and each sampled batch (see [`crate::RateLimiter`]).
    pub fn activity(&self) -> Arc<Activity> {
        self.activity.clone()
    }

    /// Minibatches handed out per second, over the last 5 seconds.
    pub fn batches_per_second(&self) -> f64 {
        self.recent_batches.per_second(Instant::now())
    }

    /// Sample streams producing from this buffer now.
    pub fn active_producers(&self) -> usize {
        self.active_producers.load(Ordering::Relaxed)
    }

    /// Admit one more producer if fewer than `max` are active: the check and the count happen in one
    /// atomic step, so concurrent requests can never pass the limit together. The permit counts the
    /// producer until it is dropped (when the stream's thread ends, or at once if the stream never
    /// starts).
    pub fn admit_producer(&self, max: usize) -> Option<ProducerPermit> {
        self.active_producers
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |active| (active < max).then_some(active + 1))
            .ok()
            .map(|_| ProducerPermit(self.active_producers.clone()))
    }

    /// Transitions that can be sampled now.
    pub fn len(&self) -> usize {
        (0..self.layout.num_envs).map(|env| self.transitions_in(env)).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub(crate) fn slot(&self, env: usize, frame: u64) -> usize {
        env * self.slots + (frame % self.slots as u64) as usize
    }

    /// The oldest absolute frame index whose transition's stacks are still whole.
    pub(crate) fn oldest_sampleable(&self, env: usize) -> u64 {
        let written = self.written[env];
        let stack = self.layout.frame_stack as u64;
        // The obs stack of the transition into frame i reaches back to frame i - frame_stack.
        let oldest = (written + stack).saturating_sub(self.slots as u64).max(1);
        match self.floors[env] {
            0 => oldest,
            floor => oldest.max(floor + stack),
        }
    }

    /// The oldest frame of `env` its slots still hold (older ones were overwritten, or lost in a
    /// restore): what a snapshot can copy.
    pub(crate) fn held_from(&self, env: usize) -> u64 {
        self.written[env].saturating_sub(self.slots as u64).max(self.floors[env])
    }

    fn transitions_in(&self, env: usize) -> usize {
        (self.written[env].saturating_sub(self.oldest_sampleable(env)) - self.first_frames[env]) as usize
    }

    /// The first frames among `env`'s sampleable frames, counted by a scan (after a restore).
    pub(crate) fn count_first_frames(&self, env: usize) -> u64 {
        let (oldest, written) = (self.oldest_sampleable(env), self.written[env]);
        (oldest..written).filter(|frame| self.flags[self.slot(env, *frame)] & FIRST_OF_EPISODE != 0).count() as u64
    }

    /// After `env` wrote frame `written - 1` into `slot` (with its flags), its sampleable frames
    /// having begun at `oldest` before: the frames that left the sampleable range (usually none or
    /// one) leave the first-frame count and the priorities; the new frame enters them (a first
    /// frame the count, a transition the priorities, at the largest priority so far).
    fn after_write(&mut self, env: usize, slot: usize, oldest: u64) {
        let (now, newest) = (self.oldest_sampleable(env), self.written[env] - 1);
        let first = |buffer: &Self, slot: usize| buffer.flags[slot] & FIRST_OF_EPISODE != 0;
        for frame in oldest..now {
            let old = self.slot(env, frame);
            debug_assert_ne!(old, slot, "a frame's stack never reaches the slot written");
            self.first_frames[env] -= u64::from(first(self, old));
            if let Some(priorities) = &mut self.priorities {
                priorities.remove(old);
            }
        }
        let entered_first = first(self, slot);
        if newest >= now {
            self.first_frames[env] += u64::from(entered_first);
        }
        if let Some(priorities) = &mut self.priorities {
            if entered_first {
                priorities.remove(slot);
            } else {
                priorities.insert(slot);
            }
        }
    }

    /// An episode starts in `env` with `frame` (a Reset, or the autoreset after an episode ended).
    pub fn record_first_frame(&mut self, env: usize, frame: &[u8], step_index: u64) {
        let index = self.written[env];
        let oldest = self.oldest_sampleable(env);
        let slot = self.write_frame(env, frame);
        self.flags[slot] = FIRST_OF_EPISODE;
        self.rewards[slot] = 0.0;
        self.episode_starts[slot] = index;
        self.step_indices[slot] = step_index;
        self.stamp(slot, None);
        self.in_episode[env] = true;
        self.after_write(env, slot, oldest);
    }

    /// `env` took a step. Steps of an env with no episode in progress are ignored (nothing to
    /// stack them on).
    pub fn record_step(&mut self, env: usize, step: &RecordedStep<'_>) {
        if !self.in_episode[env] {
            return;
        }
        debug_assert_eq!(step.action.len(), self.layout.action_bytes);
        let previous = self.slot(env, self.written[env] - 1);
        let episode_start = self.episode_starts[previous];
        let oldest = self.oldest_sampleable(env);
        let slot = self.write_frame(env, step.next_frame);
        let action_bytes = self.layout.action_bytes;
        self.actions[slot * action_bytes..(slot + 1) * action_bytes].copy_from_slice(step.action);
        self.rewards[slot] = step.reward as f32;
        self.flags[slot] = (u8::from(step.terminated) * TERMINATED) | (u8::from(step.truncated) * TRUNCATED);
        self.episode_starts[slot] = episode_start;
        self.step_indices[slot] = step.step_index;
        self.stamp(slot, step.acted);
        self.counters.inserts += 1;
        self.steps_recorded = self.steps_recorded.max(step.step_index + 1);
        if step.terminated || step.truncated {
            self.in_episode[env] = false;
        }
        self.after_write(env, slot, oldest);
        self.activity.bump();
    }

    pub(crate) fn stamp(&mut self, slot: usize, acted: Option<ActedBy>) {
        let acted = acted.unwrap_or(ActedBy { version: NO_POLICY, log_prob: 0.0, value: 0.0 });
        self.policy_versions[slot] = acted.version;
        self.log_probs[slot] = acted.log_prob;
        self.values[slot] = acted.value;
    }

    /// The episode in progress in `env` ends without a frame to show for it (its worker died): the
    /// next frame recorded must be a first frame.
    pub fn abandon_episode(&mut self, env: usize) {
        self.in_episode[env] = false;
    }

    fn write_frame(&mut self, env: usize, frame: &[u8]) -> usize {
        debug_assert_eq!(frame.len(), self.layout.frame_bytes);
        let slot = self.slot(env, self.written[env]);
        let frame_bytes = self.layout.frame_bytes;
        self.frames[slot * frame_bytes..(slot + 1) * frame_bytes].copy_from_slice(frame);
        self.written[env] += 1;
        slot
    }

    /// Draw `count` transitions uniformly with replacement.
    pub fn sample(&mut self, count: usize, rng: &mut impl Rng, out: &mut Vec<TransitionRef>) -> Result<()> {
        self.sample_windows(count, 1, rng, out)
    }

    /// Draw `count` transitions uniformly with replacement among those whose `n_step` window is
    /// complete (see [`ReplayBuffer::window`]): Acme's n-step adder inserts a transition once its
    /// n steps are in, or its episode ended, and Reverb samples only what was inserted.
    pub fn sample_windows(&mut self, count: usize, n_step: usize, rng: &mut impl Rng, out: &mut Vec<TransitionRef>) -> Result<()> {
        out.clear();
        let candidates = self.candidates();
        let no_transitions = || ReplayError::FailedPrecondition("the replay buffer holds no transitions yet".into());
        if candidates.total == 0 || self.counters.inserts == 0 {
            return Err(no_transitions());
        }
        let mut attempts = 0usize;
        while out.len() < count {
            attempts += 1;
            if attempts > 64 * count + 1024 && out.is_empty() {
                return Err(no_transitions());
            }
            out.extend(self.draw(&candidates, rng).filter(|&transition| self.window_complete(transition, n_step)));
        }
        self.counters.samples += count as u64;
        self.counters.batches += 1;
        self.recent_batches.record(Instant::now());
        self.activity.bump();
        Ok(())
    }

    /// Each env's sampleable frames now, and how many there are in all.
    fn candidates(&self) -> Candidates {
        self.candidates_from(|env| self.oldest_sampleable(env))
    }

    /// Each env's frames from `oldest(env)` to the newest.
    pub(crate) fn candidates_from(&self, oldest: impl Fn(usize) -> u64) -> Candidates {
        let ranges: Vec<(u64, u64)> = (0..self.layout.num_envs).map(|env| (oldest(env), self.written[env])).collect();
        let total = ranges.iter().map(|(oldest, written)| written.saturating_sub(*oldest)).sum();
        Candidates { ranges, total }
    }

    /// One draw, uniform over (env, frame) candidates (`total` > 0); `None` when it picked an
    /// episode's first frame, which is not a transition (the caller draws again).
    fn draw(&self, candidates: &Candidates, rng: &mut impl Rng) -> Option<TransitionRef> {
        let transition = candidates.pick(rng);
        (self.flags[self.slot(transition.env, transition.frame)] & FIRST_OF_EPISODE == 0).then_some(transition)
    }

    /// Whether `transition` (drawn earlier) is still in the buffer with its whole stack: false once
    /// the env wrote so many frames since that its slots hold newer ones.
    pub fn still_holds(&self, transition: TransitionRef) -> bool {
        transition.env < self.layout.num_envs
            && transition.frame >= self.oldest_sampleable(transition.env)
            && transition.frame < self.written[transition.env]
    }

    /// One transition drawn uniformly, as `sample` draws them, without counting it as sampled (it
    /// replaces one of a batch that the buffer no longer holds).
    pub fn draw_one(&self, rng: &mut impl Rng) -> Option<TransitionRef> {
        self.draw_one_window(1, rng)
    }

    /// The same among transitions whose `n_step` window is complete.
    pub fn draw_one_window(&self, n_step: usize, rng: &mut impl Rng) -> Option<TransitionRef> {
        let candidates = self.candidates();
        if candidates.total == 0 {
            return None;
        }
        (0..1024).find_map(|_| self.draw(&candidates, rng).filter(|&transition| self.window_complete(transition, n_step)))
    }

    /// Transitions that can be sampled now with `n_step` returns: those held, less the last
    /// `n_step - 1` of each episode in progress, whose windows are not complete yet.
    pub fn sampleable(&self, n_step: usize) -> usize {
        self.len().saturating_sub(self.incomplete_windows(n_step).count())
    }

    /// The transitions whose `n_step` windows are not complete yet: the last `n_step - 1` of each
    /// episode in progress.
    pub(crate) fn incomplete_windows(&self, n_step: usize) -> impl Iterator<Item = TransitionRef> + '_ {
        (0..self.layout.num_envs).filter(|&env| self.in_episode[env]).flat_map(move |env| {
            let oldest = self.oldest_sampleable(env);
            (1..n_step as u64)
                .map_while(move |back| self.written[env].checked_sub(back).filter(|frame| *frame >= oldest))
                .take_while(move |&frame| self.flags[self.slot(env, frame)] & FIRST_OF_EPISODE == 0)
                .map(move |frame| TransitionRef { env, frame })
        })
    }

    pub(crate) fn window_complete(&self, transition: TransitionRef, n_step: usize) -> bool {
        n_step <= 1 || self.walk_window(transition, n_step, 1.0).is_some()
    }

    /// The n-step window of a transition the buffer holds: from its step, up to `returns.n_step`
    /// steps of its episode, ending early at the step that terminated or truncated it (or at the
    /// last step recorded of an episode whose worker died). None while the window is incomplete:
    /// its episode is in progress and fewer than `n_step` steps from it are recorded.
    pub fn window(&self, transition: TransitionRef, returns: Returns) -> Option<Window> {
        self.walk_window(transition, returns.n_step, returns.discount)
    }

    fn walk_window(&self, transition: TransitionRef, n_step: usize, discount: f64) -> Option<Window> {
        let env = transition.env;
        let mut window =
            Window { steps: 0, reward: 0.0, discount: 1.0, terminated: false, truncated: false, last_frame: transition.frame };
        for k in 0..n_step as u64 {
            let frame = transition.frame + k;
            if frame >= self.written[env] {
                if self.in_episode[env] {
                    return None; // more of this window is still to come
                }
                break; // the episode ended without a flag (its worker died)
            }
            let slot = self.slot(env, frame);
            let flags = self.flags[slot];
            if k > 0 && flags & FIRST_OF_EPISODE != 0 {
                break;
            }
            window.reward += window.discount * f64::from(self.rewards[slot]);
            window.discount *= discount;
            window.steps += 1;
            window.last_frame = frame;
            if flags & TERMINATED != 0 {
                window.terminated = true;
                window.discount = 0.0;
                break;
            }
            if flags & TRUNCATED != 0 {
                window.truncated = true;
                break;
            }
        }
        Some(window)
    }

    /// The transitions of the last `steps` steps of every env, `[t][env]` (t = 0 the oldest),
    /// and the step index of t = 0; refused while fewer steps were recorded.
    pub fn rollout(&self, steps: usize) -> Result<(Vec<TransitionRef>, u64)> {
        let end = self.steps_recorded;
        let num_envs = self.layout.num_envs;
        if end < steps as u64 {
            return Err(ReplayError::FailedPrecondition(format!(
                "the rollout needs {steps} steps of every env; only {end} were taken since the session was created"
            )));
        }
        let start = end - steps as u64;
        let mut table: Vec<Option<TransitionRef>> = vec![None; steps * num_envs];
        for env in 0..num_envs {
            for frame in self.oldest_sampleable(env)..self.written[env] {
                let slot = self.slot(env, frame);
                let step = self.step_indices[slot];
                if self.flags[slot] & FIRST_OF_EPISODE == 0 && (start..end).contains(&step) {
                    table[(step - start) as usize * num_envs + env] = Some(TransitionRef { env, frame });
                }
            }
        }
        let missing = table.iter().filter(|entry| entry.is_none()).count();
        if missing > 0 {
            return Err(ReplayError::FailedPrecondition(format!(
                "{missing} of the {} transitions of steps {start}..{end} are not in the rollout (a reset or a \
                 crashed worker interrupted it); take {steps} more steps",
                table.len()
            )));
        }
        Ok((table.into_iter().map(|entry| entry.expect("checked above")).collect(), start))
    }

    /// Count a batch of transitions handed out by a sampler that did not draw them through `sample`.
    pub fn count_samples(&mut self, count: usize) {
        self.counters.samples += count as u64;
        self.counters.batches += 1;
        self.recent_batches.record(Instant::now());
        self.activity.bump();
    }

    /// Copy the observation (`next == false`) or next observation stack of a sampled transition
    /// into `out` (`frame_stack * frame_bytes`).
    pub fn copy_observation(&self, transition: TransitionRef, next: bool, out: &mut [u8]) {
        let episode_start = self.episode_starts[self.slot(transition.env, transition.frame)];
        let last = if next { transition.frame } else { transition.frame - 1 };
        self.copy_stack(transition.env, last, episode_start, out);
    }

    /// Copy the stack of a sampled transition's episode that ends at frame `last` into `out`
    /// (`frame_stack * frame_bytes`): `transition.frame - 1` is its observation, `transition.frame`
    /// its next observation, and a later frame of its window the observation n steps on.
    pub fn copy_stack_ending(&self, transition: TransitionRef, last: u64, out: &mut [u8]) {
        let episode_start = self.episode_starts[self.slot(transition.env, transition.frame)];
        self.copy_stack(transition.env, last, episode_start, out);
    }

    /// Copy the frames of a sampled transition's observation stack followed by its next frame into
    /// `out` (`(frame_stack + 1) * frame_bytes`): the first `frame_stack` frames are the
    /// observation, the last `frame_stack` the next observation (stacking pushes one frame per step,
    /// so the two stacks share all but one frame).
    pub fn copy_transition(&self, transition: TransitionRef, out: &mut [u8]) {
        let episode_start = self.episode_starts[self.slot(transition.env, transition.frame)];
        let stack = self.layout.frame_stack as u64;
        let frame_bytes = self.layout.frame_bytes;
        debug_assert_eq!(out.len(), (self.layout.frame_stack + 1) * frame_bytes);
        for (position, target) in out.chunks_exact_mut(frame_bytes).enumerate() {
            let frame = (transition.frame + position as u64).saturating_sub(stack).max(episode_start);
            let slot = self.slot(transition.env, frame);
            target.copy_from_slice(&self.frames[slot * frame_bytes..(slot + 1) * frame_bytes]);
        }
    }

    /// Copy the stack of frames ending at absolute frame `last` of `env` into `out`
    /// (`frame_stack * frame_bytes`), padding with the episode's first frame.
    pub(crate) fn copy_stack(&self, env: usize, last: u64, episode_start: u64, out: &mut [u8]) {
        let stack = self.layout.frame_stack as u64;
        let frame_bytes = self.layout.frame_bytes;
        for (position, target) in out.chunks_exact_mut(frame_bytes).enumerate() {
            let frame = (last + 1 + position as u64).saturating_sub(stack).max(episode_start);
            let slot = self.slot(env, frame);
            target.copy_from_slice(&self.frames[slot * frame_bytes..(slot + 1) * frame_bytes]);
        }
    }

    /// Gather everything but the observations of sampled transitions.
    pub fn gather_metadata(&self, refs: &[TransitionRef], batch: &mut TransitionMetadata) {
        batch.resize(refs.len(), self.layout.action_bytes);
        self.gather_metadata_at(refs, batch, 0);
    }

    /// The same for a part of a batch: `refs` are the batch's transitions from `start` on (the
    /// batch already has its length: `TransitionMetadata::resize`).
    pub fn gather_metadata_at(&self, refs: &[TransitionRef], batch: &mut TransitionMetadata, start: usize) {
        let action_bytes = self.layout.action_bytes;
        for (index, transition) in refs.iter().enumerate() {
            let index = start + index;
            let slot = self.slot(transition.env, transition.frame);
            batch.actions[index * action_bytes..(index + 1) * action_bytes]
                .copy_from_slice(&self.actions[slot * action_bytes..(slot + 1) * action_bytes]);
            batch.rewards[index] = self.rewards[slot];
            batch.terminated[index] = u8::from(self.flags[slot] & TERMINATED != 0);
            batch.truncated[index] = u8::from(self.flags[slot] & TRUNCATED != 0);
            batch.env_indices[index] = transition.env as u32;
            batch.step_indices[index] = self.step_indices[slot];
            batch.policy_versions[index] = self.policy_versions[slot];
            batch.log_probs[index] = self.log_probs[slot];
            batch.values[index] = self.values[slot];
            batch.last_frames[index] = transition.frame;
            batch.keys[index] = transition.key();
        }
    }
}

impl ReplayBuffer {
    /// Replace the one-step reward and flags gathered for `refs` (the batch's transitions from
    /// `start` on) by their n-step window's, and fill their discounts and last frames. Transitions
    /// drawn by `sample_windows` and `draw_one_window` have complete windows; one that does not
    /// gets the window of the steps recorded so far rather than stopping the stream.
    pub fn gather_returns_at(&self, refs: &[TransitionRef], returns: Returns, batch: &mut TransitionMetadata, start: usize) {
        for (index, transition) in refs.iter().enumerate() {
            let index = start + index;
            let window = self.window(*transition, returns).unwrap_or_else(|| {
                self.walk_window(*transition, (self.written[transition.env] - transition.frame) as usize, returns.discount)
                    .expect("a window up to the last frame written is complete")
            });
            batch.rewards[index] = window.reward as f32;
            batch.discounts[index] = window.discount as f32;
            batch.terminated[index] = u8::from(window.terminated);
            batch.truncated[index] = u8::from(window.truncated);
            batch.last_frames[index] = window.last_frame;
        }
    }
}

/// Everything of sampled transitions but their observations.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TransitionMetadata {
    pub len: usize,
    /// [len, action_bytes]
    pub actions: Vec<u8>,
    pub rewards: Vec<f32>,
    pub terminated: Vec<u8>,
    pub truncated: Vec<u8>,
    /// Which environment each transition came from.
    pub env_indices: Vec<u32>,
    /// The session step (Step call index) that produced each transition.
    pub step_indices: Vec<u64>,
    /// The server-side policy version that acted (`NO_POLICY`: none), the action's log-probability
    /// and the model's value.
    pub policy_versions: Vec<i32>,
    pub log_probs: Vec<f32>,
    pub values: Vec<f32>,
    /// With n-step returns: the bootstrap's factor (see [`Window::discount`]).
    pub discounts: Vec<f32>,
    /// The frame each next observation's stack ends at (the transition's own next frame for one
    /// step).
    pub last_frames: Vec<u64>,
    /// Each transition's key ([`TransitionRef::key`]): what `UpdatePriorities` names it by.
    pub keys: Vec<u64>,
    /// In a prioritized batch: each draw's probability, and its importance weight (see
    /// [`crate::importance_weights`]).
    pub probabilities: Vec<f64>,
    pub weights: Vec<f32>,
    /// In a sequence batch, per step (see [`crate::Sequence`]): the step's observation is its
    /// episode's first, its episode's last (no step was taken from it), the last of an episode that
    /// terminated; and whether the step holds data at all (0: padding after its episode's end).
    pub is_first: Vec<u8>,
    pub is_last: Vec<u8>,
    pub is_terminal: Vec<u8>,
    pub mask: Vec<u8>,
}

impl TransitionMetadata {
    pub(crate) fn resize(&mut self, len: usize, action_bytes: usize) {
        self.len = len;
        self.actions.resize(len * action_bytes, 0);
        self.rewards.resize(len, 0.0);
        self.terminated.resize(len, 0);
        self.truncated.resize(len, 0);
        self.env_indices.resize(len, 0);
        self.step_indices.resize(len, 0);
        self.policy_versions.resize(len, NO_POLICY);
        self.log_probs.resize(len, 0.0);
        self.values.resize(len, 0.0);
        self.discounts.resize(len, 0.0);
        self.last_frames.resize(len, 0);
        self.keys.resize(len, 0);
        self.probabilities.resize(len, 0.0);
        self.weights.resize(len, 1.0);
    }

    /// The same with the sequence flags (every row a step of a sequence).
    pub(crate) fn resize_steps(&mut self, len: usize, action_bytes: usize) {
        self.resize(len, action_bytes);
        for flags in [&mut self.is_first, &mut self.is_last, &mut self.is_terminal, &mut self.mask] {
            flags.resize(len, 0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_that_overflow_are_refused_not_wrapped() {
        let layout = |capacity| ReplayLayout {
            kind: BufferKind::Replay,
            capacity,
            num_envs: 1,
            frame_stack: 1,
            frame_bytes: 16,
            action_bytes: 8,
        };
        // (capacity + 1) * 45 once wrapped to 29 bytes (before the actor columns): the budget passed and the allocation aborted.
        for capacity in [409_927_646_082_434_480, usize::MAX, MAX_CAPACITY + 1] {
            assert_eq!(layout(capacity).memory_bytes(), if capacity > MAX_CAPACITY * 2 { usize::MAX } else { (capacity + 1) * 57 });
            let error = layout(capacity).validate().unwrap_err().to_string();
            assert!(error.contains("above the most a buffer can hold"), "{error}");
            assert!(ReplayBuffer::new(layout(capacity)).is_err());
        }
        let rollout = ReplayLayout::rollout(usize::MAX, 256, 1, 16, 8);
        assert_eq!((rollout.capacity, rollout.memory_bytes()), (usize::MAX, usize::MAX));
        assert!(rollout.validate().is_err());
        // Within the capacity cap but not addressable: huge frames.
        let huge_frames = ReplayLayout { frame_bytes: usize::MAX / 2, ..layout(1000) };
        assert!(huge_frames.validate().unwrap_err().to_string().contains("cannot be addressed"));
        layout(1000).validate().unwrap();
    }

    #[test]
    fn producers_are_admitted_up_to_the_limit_at_once() {
        let buffer = ReplayBuffer::new(ReplayLayout::rollout(4, 2, 1, 4, 4)).unwrap();
        let permits: Vec<_> = (0..3).map(|_| buffer.admit_producer(3).expect("room for three")).collect();
        assert!(buffer.admit_producer(3).is_none());
        assert_eq!(buffer.active_producers(), 3);
        drop(permits);
        assert_eq!(buffer.active_producers(), 0);
        assert!(buffer.admit_producer(3).is_some());
    }

    #[test]
    fn the_batch_rate_counts_the_last_five_seconds() {
        let mut recent = RecentBatches::default();
        let start = Instant::now();
        assert_eq!(recent.per_second(start), 0.0);
        // 10 batches per second for 8 seconds.
        for tenth in 0..80 {
            recent.record(start + Duration::from_millis(100 * tenth));
        }
        let now = start + Duration::from_millis(7950);
        assert!((recent.per_second(now) - 10.0).abs() <= 0.2, "{}", recent.per_second(now));
        assert!(recent.times.len() <= 52, "older batches are dropped");
        // Silence: the rate falls to zero once the window has passed.
        assert_eq!(recent.per_second(now + Duration::from_secs(6)), 0.0);
        // A young stream counts at least one second: 3 batches in 0.2 s read as 3 per second.
        let mut young = RecentBatches::default();
        for tenth in 0..3 {
            young.record(start + Duration::from_millis(100 * tenth));
        }
        assert_eq!(young.per_second(start + Duration::from_millis(200)), 3.0);
    }
}
