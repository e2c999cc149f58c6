//! Sequences of consecutive steps of one environment, for recurrent learners (R2D2's burn-in and
//! period: Acme's `SequenceAdder`), world models (Dreamer's `is_first`/`is_last`/`is_terminal`,
//! windows across episodes) and the futures of SPR and TACO (the K steps after t, masked after the
//! episode ends). Read for the semantics, not copied: Acme `adders/reverb/sequence.py`,
//! danijar/dreamerv3 `embodied/replay`, mila-iqia/spr `src/rlpyt_utils.py`.
//!
//! Step i of a sequence that starts at frame s of an env is frame s + i: its observation is the
//! stack ending at that frame (padded at its episode's start, as every stack is); its action,
//! reward, terminated and truncated are those of the step taken *from* it (recorded in the next
//! frame's slot), zero where none was (the episode's last frame). Frames stay stored once: a
//! sequence is gathered from the same ring as single transitions.

use rand::Rng;

use crate::buffer::{Candidates, ReplayBuffer, TransitionMetadata, TransitionRef, FIRST_OF_EPISODE, NO_POLICY, TERMINATED, TRUNCATED};
use crate::error::{ReplayError, Result};

/// The longest sequence a request may ask for (Acme's R2D2 uses 80 + 40 burn-in, DreamerV3 64).
pub const MAX_SEQUENCE_LENGTH: usize = 1024;

/// Which windows a sequence stream draws.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Boundary {
    /// Windows that start in an episode, at its first frame or a multiple of `period` steps after
    /// it, with at least one step taken after the burn-in; steps after the episode's last frame
    /// are padding (`mask` 0, zero observations and fields): Acme's `EndBehavior.ZERO_PAD`, which
    /// R2D2 uses, and SPR's masked futures.
    #[default]
    WithinEpisode,
    /// Windows of consecutive frames of one env wherever they fall (at frames that are multiples
    /// of `period`), across episode ends, flagged by `is_first`, `is_last` and `is_terminal`:
    /// Dreamer's replay.
    AcrossEpisodes,
}

/// A sequence request: `length` steps per sequence, the first `burn_in` of them context only.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sequence {
    /// Steps per sequence, burn-in included (Acme's `sequence_length`).
    pub length: usize,
    /// Leading steps a recurrent learner only unrolls its state over (R2D2: 40 of 120); a
    /// within-episode window must take a step after them.
    pub burn_in: usize,
    /// Windows start every `period` steps (1: at every step).
    pub period: usize,
    pub boundary: Boundary,
}

impl Sequence {
    /// Checks the bounds: `length` in `1..=MAX_SEQUENCE_LENGTH`, `burn_in < length`, `period` in
    /// `1..=MAX_SEQUENCE_LENGTH`.
    pub fn new(length: usize, burn_in: usize, period: usize, boundary: Boundary) -> Result<Self> {
        let invalid = |message: String| Err(ReplayError::InvalidArgument(message));
        if !(1..=MAX_SEQUENCE_LENGTH).contains(&length) {
            return invalid(format!("sequence length must be between 1 and {MAX_SEQUENCE_LENGTH} steps, got {length}"));
        }
        if burn_in >= length {
            return invalid(format!(
                "sequence burn_in ({burn_in}) must be below its length ({length}): the length counts the burn-in, and \
                 a sequence needs steps after it to learn from"
            ));
        }
        if !(1..=MAX_SEQUENCE_LENGTH).contains(&period) {
            return invalid(format!("sequence period must be between 1 and {MAX_SEQUENCE_LENGTH} steps, got {period}"));
        }
        Ok(Self { length, burn_in, period, boundary })
    }

    /// Frames of one env a sequence needs held at once: its steps, the frame after the last (whose
    /// slot holds the last step's action) and the stack the first observation reaches back over.
    pub fn frames_needed(&self, frame_stack: usize) -> usize {
        self.length + frame_stack
    }
}

/// What follows a frame in its env's ring.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum After {
    /// A step was taken from the frame; its action and outcome are in this slot.
    Step(usize),
    /// The frame is the last of its episode (terminated, truncated, or its worker died).
    End,
    /// The frame is the newest of an episode still running: what follows is not known yet.
    Unknown,
}

impl ReplayBuffer {
    /// The oldest frame of `env` whose own stack is whole: one before the oldest transition's next
    /// frame (that transition's observation is this frame's stack).
    fn oldest_observation(&self, env: usize) -> u64 {
        self.oldest_sampleable(env) - 1
    }

    /// What follows frame `frame` (< written) of `env`.
    fn after(&self, env: usize, frame: u64) -> After {
        if frame + 1 < self.written[env] {
            let next = self.slot(env, frame + 1);
            if self.flags[next] & FIRST_OF_EPISODE != 0 {
                After::End
            } else {
                After::Step(next)
            }
        } else if self.in_episode[env] {
            After::Unknown
        } else {
            After::End
        }
    }

    /// Whether a sequence can start at frame `start` of `env` now: the frame is held with its
    /// stack, it is where `sequence`'s rule lets windows start, and every step of the window is
    /// known (recorded, or past its episode's end).
    pub fn sequence_starts_at(&self, env: usize, start: u64, sequence: &Sequence) -> bool {
        if env >= self.layout.num_envs || start < self.oldest_observation(env) || start >= self.written[env] {
            return false;
        }
        let period = sequence.period as u64;
        match sequence.boundary {
            Boundary::AcrossEpisodes => {
                let last = start + sequence.length as u64 - 1;
                start.is_multiple_of(period) && last < self.written[env] && self.after(env, last) != After::Unknown
            }
            Boundary::WithinEpisode => {
                let episode_start = self.episode_starts[self.slot(env, start)];
                if !(start - episode_start).is_multiple_of(period) {
                    return false;
                }
                for step in 0..sequence.length {
                    match self.after(env, start + step as u64) {
                        After::Step(_) => {}
                        // The steps after the burn-in hold at least one transition.
                        After::End => return step > sequence.burn_in,
                        After::Unknown => return false,
                    }
                }
                true
            }
        }
    }

    /// The frames a sequence may start at: every held frame whose stack is whole.
    fn sequence_candidates(&self) -> Candidates {
        self.candidates_from(|env| self.oldest_observation(env))
    }

    /// One start drawn uniformly among those `sequence_starts_at` allows, by rejection from the
    /// held frames (uniform over frames, then kept if a window may start there); None when
    /// `attempts` draws found none.
    fn draw_sequence(&self, candidates: &Candidates, sequence: &Sequence, attempts: usize, rng: &mut impl Rng) -> Option<TransitionRef> {
        if candidates.total == 0 {
            return None;
        }
        (0..attempts).find_map(|_| {
            let start = candidates.pick(rng);
            self.sequence_starts_at(start.env, start.frame, sequence).then_some(start)
        })
    }

    /// Draws `count` sequence starts uniformly with replacement (each a [`TransitionRef`] whose
    /// `frame` is the sequence's first frame) and counts their steps as sampled. Ok(false), with
    /// nothing drawn or counted, when no window can start yet (episodes shorter than the burn-in,
    /// or fewer steps recorded than a window needs): the stream waits for more inserts.
    pub fn sample_sequences(&mut self, count: usize, sequence: &Sequence, rng: &mut impl Rng, out: &mut Vec<TransitionRef>) -> Result<bool> {
        out.clear();
        if self.counters.inserts == 0 {
            return Ok(false);
        }
        // Rejection keeps about one frame in `period` (and fewer near episode ends).
        let attempts = (64 * count + 1024).saturating_mul(sequence.period);
        let candidates = self.sequence_candidates();
        let Some(first) = self.draw_sequence(&candidates, sequence, attempts, rng) else { return Ok(false) };
        out.push(first);
        while out.len() < count {
            // A window exists (the first), so each attempt succeeds with positive probability.
            out.extend(self.draw_sequence(&candidates, sequence, attempts, rng));
        }
        self.count_samples(count * sequence.length);
        Ok(true)
    }

    /// One start drawn as `sample_sequences` draws, without counting it (it replaces a sequence of
    /// a batch whose first frame the buffer overwrote meanwhile).
    pub fn draw_one_sequence(&self, sequence: &Sequence, rng: &mut impl Rng) -> Option<TransitionRef> {
        self.draw_sequence(&self.sequence_candidates(), sequence, (64 + 1024) * sequence.period, rng)
    }

    /// Whether the sequence starting at `start` (drawn earlier) is still held: its first frame's
    /// stack is (the later frames are newer, so they are too).
    pub fn still_holds_sequence(&self, start: TransitionRef) -> bool {
        start.env < self.layout.num_envs && start.frame >= self.oldest_observation(start.env) && start.frame < self.written[start.env]
    }

    /// Fills rows `row..row + sequence.length` of `batch` (sized by `resize_steps`) with the
    /// sequence starting at `start`: each step's action, reward, flags, indices and, with
    /// `discount`, the factor of its bootstrap (`discount`, 0 where the step terminated its episode
    /// or where no step was taken). Returns the steps that hold data (the rest are padding).
    pub fn gather_sequence_at(
        &self,
        start: TransitionRef,
        sequence: &Sequence,
        discount: Option<f64>,
        batch: &mut TransitionMetadata,
        row: usize,
    ) -> usize {
        let (env, action_bytes) = (start.env, self.layout.action_bytes);
        let mut ended = false;
        let mut real = 0;
        for step in 0..sequence.length {
            let index = row + step;
            let frame = start.frame + step as u64;
            // Every field starts as "no step": zeros, no policy. Padding after the episode's end
            // (within-episode windows only) stays so; a frame fills what it has.
            let actions = &mut batch.actions[index * action_bytes..(index + 1) * action_bytes];
            actions.fill(0);
            batch.rewards[index] = 0.0;
            batch.terminated[index] = 0;
            batch.truncated[index] = 0;
            batch.env_indices[index] = env as u32;
            batch.step_indices[index] = 0;
            batch.policy_versions[index] = NO_POLICY;
            batch.log_probs[index] = 0.0;
            batch.values[index] = 0.0;
            batch.discounts[index] = 0.0;
            batch.keys[index] = 0;
            batch.last_frames[index] = 0;
            for flags in [&mut batch.is_first, &mut batch.is_last, &mut batch.is_terminal, &mut batch.mask] {
                flags[index] = 0;
            }
            if ended || frame >= self.written[env] {
                continue;
            }
            real += 1;
            let slot = self.slot(env, frame);
            match self.after(env, frame) {
                After::Step(next) => {
                    actions.copy_from_slice(&self.actions[next * action_bytes..(next + 1) * action_bytes]);
                    batch.rewards[index] = self.rewards[next];
                    batch.terminated[index] = u8::from(self.flags[next] & TERMINATED != 0);
                    batch.truncated[index] = u8::from(self.flags[next] & TRUNCATED != 0);
                    batch.step_indices[index] = self.step_indices[next];
                    batch.policy_versions[index] = self.policy_versions[next];
                    batch.log_probs[index] = self.log_probs[next];
                    batch.values[index] = self.values[next];
                    if self.flags[next] & TERMINATED == 0 {
                        batch.discounts[index] = discount.unwrap_or(1.0) as f32;
                    }
                }
                After::End | After::Unknown => {
                    // The step that produced the frame (the reset's, for a first frame).
                    batch.step_indices[index] = self.step_indices[slot];
                    batch.is_last[index] = 1;
                    ended = sequence.boundary == Boundary::WithinEpisode;
                }
            }
            batch.keys[index] = TransitionRef { env, frame }.key();
            batch.last_frames[index] = frame;
            batch.is_first[index] = u8::from(self.flags[slot] & FIRST_OF_EPISODE != 0);
            batch.is_terminal[index] = u8::from(self.flags[slot] & TERMINATED != 0);
            batch.mask[index] = 1;
        }
        real
    }

    /// Copies the observation stacks of the first `steps` steps of the sequence starting at
    /// `start` into `out` (`steps * frame_stack * frame_bytes`), each within its own episode.
    pub fn copy_sequence(&self, start: TransitionRef, steps: usize, out: &mut [u8]) {
        let stack_bytes = self.layout.frame_stack * self.layout.frame_bytes;
        for (step, target) in out.chunks_exact_mut(stack_bytes).take(steps).enumerate() {
            let frame = start.frame + step as u64;
            let episode_start = self.episode_starts[self.slot(start.env, frame)];
            self.copy_stack(start.env, frame, episode_start, target);
        }
    }
}
