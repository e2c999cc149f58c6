//! Proportional prioritized sampling (Schaul et al. 2016, "Prioritized Experience Replay"): a
//! transition is drawn with probability `p_i^alpha / sum_k p_k^alpha`, new transitions enter at the
//! largest priority seen so far, and a learner's TD errors replace priorities after each step.
//!
//! [`SumTree`] holds one weight per replay slot and finds the slot at a prefix sum in O(log n), as
//! Reverb's `PrioritizedSelector` and Dopamine's `SumTree` do (read for the semantics, not copied).
//! [`Priorities`] keeps each slot's priority and one tree per exponent that a stream samples with.

use rand::Rng;

use crate::buffer::{ReplayBuffer, TransitionRef, FIRST_OF_EPISODE};
use crate::error::{ReplayError, Result};

/// A binary tree of sums over `len` non-negative leaves: setting a leaf and finding the leaf at a
/// prefix sum both take O(log len). Each inner node is recomputed from its children on every
/// update (never adjusted by a difference), so no rounding error accumulates.
#[derive(Clone, Debug)]
pub struct SumTree {
    /// Leaves: `len` rounded up to a power of two (at least 1).
    width: usize,
    len: usize,
    /// Heap order: the root is node 1, node i has children 2i and 2i + 1, leaf j is node width + j.
    nodes: Vec<f64>,
}

impl SumTree {
    /// A tree of `len` zero leaves.
    pub fn new(len: usize) -> Self {
        let width = len.max(1).next_power_of_two();
        Self { width, len, nodes: vec![0.0; 2 * width] }
    }

    /// A tree of the given leaves, built bottom-up in O(len).
    pub fn from_leaves(leaves: impl ExactSizeIterator<Item = f64>) -> Self {
        let mut tree = Self::new(leaves.len());
        for (node, weight) in tree.nodes[tree.width..].iter_mut().zip(leaves) {
            debug_assert!(weight.is_finite() && weight >= 0.0, "a leaf of {weight}");
            *node = weight;
        }
        for node in (1..tree.width).rev() {
            tree.nodes[node] = tree.nodes[2 * node] + tree.nodes[2 * node + 1];
        }
        tree
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The sum of all leaves.
    pub fn total(&self) -> f64 {
        self.nodes[1]
    }

    pub fn get(&self, leaf: usize) -> f64 {
        debug_assert!(leaf < self.len);
        self.nodes[self.width + leaf]
    }

    /// Set leaf `leaf` to `weight` (finite, non-negative).
    pub fn set(&mut self, leaf: usize, weight: f64) {
        debug_assert!(leaf < self.len && weight.is_finite() && weight >= 0.0, "leaf {leaf} of {} set to {weight}", self.len);
        let mut node = self.width + leaf;
        self.nodes[node] = weight;
        while node > 1 {
            node /= 2;
            self.nodes[node] = self.nodes[2 * node] + self.nodes[2 * node + 1];
        }
    }

    /// The leaf whose share of the cumulative sum holds `prefix`: leaf j for `prefix` in
    /// `[sum of leaves before j, that + leaf j)`. Never a zero leaf while the total is positive: a
    /// prefix that rounding carries past a subtree's end stays in its last positive leaf. None when
    /// every leaf is zero.
    pub fn find(&self, prefix: f64) -> Option<usize> {
        if self.total() <= 0.0 {
            return None;
        }
        let mut prefix = prefix.max(0.0);
        let mut node = 1;
        while node < self.width {
            let (left, right) = (self.nodes[2 * node], self.nodes[2 * node + 1]);
            if prefix < left || right <= 0.0 {
                node *= 2;
            } else {
                prefix -= left;
                node = 2 * node + 1;
            }
        }
        Some(node - self.width)
    }

    /// A leaf drawn with probability proportional to its weight; None when every leaf is zero.
    pub fn draw(&self, rng: &mut impl Rng) -> Option<usize> {
        self.find(rng.random::<f64>() * self.total())
    }
}

/// The bound on prioritized streams' distinct exponents at one time: each needs a tree of its own
/// (16 bytes per slot).
pub const MAX_EXPONENTS: usize = 4;

/// How a prioritized stream samples: its two exponents, checked by [`Prioritized::new`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prioritized {
    /// alpha: draws are proportional to priority^alpha (0: uniform over the transitions held).
    pub exponent: f64,
    /// beta: the importance weight of a draw is `(N * P(i))^-beta`, divided by the batch's largest.
    pub importance_exponent: f64,
}

impl Prioritized {
    /// Both exponents in [0, 1] (Schaul et al.: alpha 0.6 or 0.7, beta annealed from 0.4 or 0.5
    /// to 1; Rainbow: 0.5 and 0.4 to 1).
    pub fn new(exponent: f64, importance_exponent: f64) -> Result<Self> {
        for (name, value) in [("priority_exponent", exponent), ("importance_sampling_exponent", importance_exponent)] {
            if !(0.0..=1.0).contains(&value) {
                return Err(ReplayError::InvalidArgument(format!("{name} must be in [0, 1], got {value}")));
            }
        }
        Ok(Self { exponent, importance_exponent })
    }
}

/// A slot that holds no sampleable transition (never written, an episode's first frame, or a
/// frame whose stack reaches overwritten frames).
const ABSENT: f64 = -1.0;

/// The priority a transition starts at before any was set (Schaul et al.; Dopamine's
/// `max_recorded_priority` starts at 1 too).
pub const INITIAL_PRIORITY: f64 = 1.0;

/// Each slot's priority and a sum tree of priority^exponent per exponent in use.
#[derive(Clone, Debug)]
pub(crate) struct Priorities {
    raw: Vec<f64>,
    /// The largest priority set so far: what a new transition enters at.
    max: f64,
    trees: Vec<ExponentTree>,
}

#[derive(Clone, Debug)]
struct ExponentTree {
    exponent: f64,
    /// Streams sampling with this exponent now.
    users: usize,
    tree: SumTree,
}

fn weight(priority: f64, exponent: f64) -> f64 {
    if priority < 0.0 {
        0.0
    } else if exponent == 0.0 {
        1.0
    } else {
        priority.powf(exponent)
    }
}

/// Bytes prioritized sampling may add to a buffer of `slots` slots for one exponent: each slot's
/// priority (8 bytes) and the exponent's sum tree (two f64 per leaf, leaves rounded up to a power of
/// two). A prioritized stream's memory reservation counts them.
pub fn priority_memory_bytes(slots: usize) -> u64 {
    let leaves = slots.max(1).next_power_of_two() as u64;
    8 * slots as u64 + 16 * leaves
}

impl Priorities {
    /// Every slot absent.
    pub(crate) fn new(slots: usize) -> Self {
        Self { raw: vec![ABSENT; slots], max: INITIAL_PRIORITY, trees: Vec::new() }
    }

    pub(crate) fn max(&self) -> f64 {
        self.max
    }

    /// The slot's priority, None where it holds no sampleable transition.
    pub(crate) fn get(&self, slot: usize) -> Option<f64> {
        let priority = self.raw[slot];
        (priority >= 0.0).then_some(priority)
    }

    /// A new transition in `slot`, at the largest priority so far.
    pub(crate) fn insert(&mut self, slot: usize) {
        self.put(slot, self.max);
    }

    /// `slot` no longer holds a sampleable transition.
    pub(crate) fn remove(&mut self, slot: usize) {
        if self.raw[slot] >= 0.0 {
            self.put(slot, ABSENT);
        }
    }

    /// Replace the priority of a transition `slot` holds (finite, non-negative: checked by the
    /// caller); the largest priority seen grows with it.
    pub(crate) fn update(&mut self, slot: usize, priority: f64) {
        debug_assert!(self.raw[slot] >= 0.0 && priority.is_finite() && priority >= 0.0);
        self.max = self.max.max(priority);
        self.put(slot, priority);
    }

    fn put(&mut self, slot: usize, priority: f64) {
        self.raw[slot] = priority;
        for tree in &mut self.trees {
            tree.tree.set(slot, weight(priority, tree.exponent));
        }
    }

    /// Start sampling with `exponent`: its tree is built (O(slots)) unless a stream uses it
    /// already. Refused while MAX_EXPONENTS others are in use.
    pub(crate) fn acquire(&mut self, exponent: f64) -> Result<()> {
        if let Some(tree) = self.trees.iter_mut().find(|tree| tree.exponent == exponent) {
            tree.users += 1;
            return Ok(());
        }
        if self.trees.len() >= MAX_EXPONENTS {
            let used: Vec<String> = self.trees.iter().map(|tree| tree.exponent.to_string()).collect();
            return Err(ReplayError::FailedPrecondition(format!(
                "this replay's prioritized streams sample with {MAX_EXPONENTS} priority exponents already ({}); \
                 a stream with exponent {exponent} can start when one of them ends",
                used.join(", ")
            )));
        }
        let tree = SumTree::from_leaves(self.raw.iter().map(|&priority| weight(priority, exponent)));
        self.trees.push(ExponentTree { exponent, users: 1, tree });
        Ok(())
    }

    /// A stream that sampled with `exponent` ended; its tree goes with its last user.
    pub(crate) fn release(&mut self, exponent: f64) {
        if let Some(index) = self.trees.iter().position(|tree| tree.exponent == exponent) {
            self.trees[index].users -= 1;
            if self.trees[index].users == 0 {
                self.trees.swap_remove(index);
            }
        }
    }

    /// The tree of `exponent` (acquired by the caller's stream).
    pub(crate) fn tree(&self, exponent: f64) -> Option<&SumTree> {
        self.trees.iter().find(|tree| tree.exponent == exponent).map(|tree| &tree.tree)
    }

    /// Exponents in use and their streams.
    #[cfg(test)]
    fn exponents(&self) -> Vec<(f64, usize)> {
        self.trees.iter().map(|tree| (tree.exponent, tree.users)).collect()
    }

    /// A slot's weight under `exponent`.
    pub(crate) fn weight(&self, slot: usize, exponent: f64) -> f64 {
        weight(self.raw[slot], exponent)
    }
}

/// What an `UpdatePriorities` call changed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PriorityUpdate {
    /// Transitions whose priority was replaced.
    pub updated: usize,
    /// Keys of transitions the buffer no longer holds (overwritten since they were sampled), left
    /// alone as Reverb leaves keys it does not hold.
    pub missing: usize,
}

/// The most keys one `UpdatePriorities` call may carry.
pub const MAX_PRIORITY_UPDATES: usize = 1 << 16;

impl ReplayBuffer {
    /// A prioritized stream starts sampling with `exponent`: the first one makes every transition
    /// held enter at [`INITIAL_PRIORITY`], and from then on each new transition enters at the
    /// largest priority set so far.
    pub fn acquire_priorities(&mut self, exponent: f64) -> Result<()> {
        if self.priorities.is_none() {
            self.priorities = Some(self.every_transition_at(INITIAL_PRIORITY));
        }
        self.priorities.as_mut().expect("set above").acquire(exponent)
    }

    /// A prioritized stream that sampled with `exponent` ended. The priorities stay.
    pub fn release_priorities(&mut self, exponent: f64) {
        if let Some(priorities) = &mut self.priorities {
            priorities.release(exponent);
        }
    }

    /// The priority of a transition the buffer holds (None: not held, or no prioritized stream
    /// sampled this buffer yet).
    pub fn priority(&self, transition: TransitionRef) -> Option<f64> {
        let priorities = self.priorities.as_ref()?;
        if !self.still_holds(transition) {
            return None;
        }
        priorities.get(self.slot(transition.env, transition.frame))
    }

    /// The largest priority set so far: what new transitions enter at.
    pub fn max_priority(&self) -> Option<f64> {
        self.priorities.as_ref().map(Priorities::max)
    }

    /// Priorities with every transition the buffer can sample at `priority` (also the largest set).
    fn every_transition_at(&self, priority: f64) -> Priorities {
        let mut priorities = Priorities::new(self.flags.len());
        priorities.max = priority;
        for env in 0..self.layout.num_envs {
            for frame in self.oldest_sampleable(env)..self.written[env] {
                let slot = self.slot(env, frame);
                if self.flags[slot] & FIRST_OF_EPISODE == 0 {
                    priorities.insert(slot);
                }
            }
        }
        priorities
    }

    /// The transition `slot` holds (one with a priority: its env wrote at least one frame).
    fn transition_in(&self, slot: usize) -> TransitionRef {
        let (env, position, slots) = (slot / self.slots, (slot % self.slots) as u64, self.slots as u64);
        let last = self.written[env] - 1;
        TransitionRef { env, frame: last - (last % slots + slots - position) % slots }
    }

    /// The weight under `exponent` that the sum tree gives transitions whose `n_step` windows are
    /// still incomplete (never drawn), and the weight of those that can be drawn.
    fn drawable_weight(&self, n_step: usize, exponent: f64) -> Result<f64> {
        let tree = self.tree(exponent)?;
        let priorities = self.priorities.as_ref().expect("a tree exists");
        let incomplete: f64 = self
            .incomplete_windows(n_step)
            .map(|transition| priorities.weight(self.slot(transition.env, transition.frame), exponent))
            .sum();
        Ok(tree.total() - incomplete)
    }

    /// The sum tree of a prioritized stream's `exponent`.
    fn tree(&self, exponent: f64) -> Result<&SumTree> {
        self.priorities
            .as_ref()
            .and_then(|priorities| priorities.tree(exponent))
            .ok_or_else(|| ReplayError::FailedPrecondition(format!("no prioritized stream samples with exponent {exponent}")))
    }

    /// Draw `count` transitions with replacement, each with probability `priority^exponent` over
    /// the sum of that over the transitions whose `n_step` windows are complete; `probabilities`
    /// gets each draw's. The stream drawing must hold `exponent` ([`Self::acquire_priorities`]).
    /// Returns how many transitions could be drawn (the importance weights' N).
    pub fn sample_prioritized(
        &mut self,
        count: usize,
        n_step: usize,
        exponent: f64,
        rng: &mut impl Rng,
        out: &mut Vec<TransitionRef>,
        probabilities: &mut Vec<f64>,
    ) -> Result<usize> {
        out.clear();
        probabilities.clear();
        let sampleable = self.sampleable(n_step);
        if self.counters.inserts == 0 || sampleable == 0 {
            return Err(ReplayError::FailedPrecondition("the replay buffer holds no transitions yet".into()));
        }
        let drawable = self.drawable_weight(n_step, exponent)?;
        let all_zero = || {
            ReplayError::FailedPrecondition(
                "every transition that can be sampled has priority 0 (UpdatePriorities set them so): with a positive \
                 priority_exponent none can be drawn"
                    .into(),
            )
        };
        if drawable <= 0.0 {
            return Err(all_zero());
        }
        let mut attempts = 0usize;
        while out.len() < count {
            attempts += 1;
            if attempts > 64 * count + 1024 && out.is_empty() {
                return Err(all_zero());
            }
            if let Some((transition, probability)) = self.draw_prioritized(n_step, exponent, drawable, rng)? {
                out.push(transition);
                probabilities.push(probability);
            }
        }
        self.count_samples(count);
        Ok(sampleable)
    }

    /// One draw as `sample_prioritized` draws, without counting it as sampled (it replaces one of
    /// a batch that the buffer no longer holds); None when nothing can be drawn.
    pub fn draw_one_prioritized(&self, n_step: usize, exponent: f64, rng: &mut impl Rng) -> Option<(TransitionRef, f64)> {
        let drawable = self.drawable_weight(n_step, exponent).ok()?;
        if drawable <= 0.0 {
            return None;
        }
        (0..1024).find_map(|_| self.draw_prioritized(n_step, exponent, drawable, rng).ok().flatten())
    }

    fn draw_prioritized(
        &self,
        n_step: usize,
        exponent: f64,
        drawable: f64,
        rng: &mut impl Rng,
    ) -> Result<Option<(TransitionRef, f64)>> {
        let tree = self.tree(exponent)?;
        let Some(slot) = tree.draw(rng) else {
            return Ok(None);
        };
        let transition = self.transition_in(slot);
        Ok(self.window_complete(transition, n_step).then(|| (transition, tree.get(slot) / drawable)))
    }

    /// Replace the priorities of the transitions named by `keys` (from sampled batches) with
    /// `priorities`, finite and non-negative. Everything is checked before anything changes; keys
    /// of transitions the buffer overwrote since are skipped.
    pub fn update_priorities(&mut self, keys: &[u64], priorities: &[f64]) -> Result<PriorityUpdate> {
        if keys.len() != priorities.len() {
            return Err(ReplayError::InvalidArgument(format!(
                "keys and priorities must have one entry each per transition; got {} keys and {} priorities",
                keys.len(),
                priorities.len()
            )));
        }
        if keys.len() > MAX_PRIORITY_UPDATES {
            return Err(ReplayError::InvalidArgument(format!(
                "at most {MAX_PRIORITY_UPDATES} priorities per update; got {}",
                keys.len()
            )));
        }
        if let Some((index, value)) = priorities.iter().enumerate().find(|(_, value)| !(value.is_finite() && **value >= 0.0)) {
            return Err(ReplayError::InvalidArgument(format!(
                "priorities must be finite and non-negative; priorities[{index}] is {value}"
            )));
        }
        let num_envs = self.layout.num_envs;
        if let Some((index, key)) = keys.iter().enumerate().find(|(_, key)| TransitionRef::from_key(**key).env >= num_envs) {
            return Err(ReplayError::InvalidArgument(format!(
                "keys[{index}] ({key}) is not a key of this replay (its env {} is not below {num_envs}): keys come from a \
                 prioritized batch's \"key\" field",
                TransitionRef::from_key(*key).env
            )));
        }
        if self.priorities.is_none() {
            return Err(ReplayError::FailedPrecondition(
                "no prioritized stream sampled this replay: priorities exist from the first SampleBatches with \
                 sampler PRIORITIZED on"
                    .into(),
            ));
        }
        let mut report = PriorityUpdate::default();
        for (&key, &priority) in keys.iter().zip(priorities) {
            let transition = TransitionRef::from_key(key);
            let slot = self.slot(transition.env, transition.frame);
            // `priority` is None for a key the buffer no longer holds (its slot holds a newer frame).
            if self.priority(transition).is_some() {
                self.priorities.as_mut().expect("checked above").update(slot, priority);
                report.updated += 1;
            } else {
                report.missing += 1;
            }
        }
        Ok(report)
    }
}

impl ReplayBuffer {
    /// For a snapshot: the largest priority set (f64), then the key (u64) and priority (f64) of each
    /// transition that has one, little-endian; None before any prioritized stream.
    pub(crate) fn export_priorities(&self) -> Option<Vec<u8>> {
        let priorities = self.priorities.as_ref()?;
        let mut out = Vec::with_capacity(8 + 16 * self.len());
        out.extend_from_slice(&priorities.max().to_le_bytes());
        for env in 0..self.layout.num_envs {
            for frame in self.oldest_sampleable(env)..self.written[env] {
                if let Some(priority) = priorities.get(self.slot(env, frame)) {
                    out.extend_from_slice(&TransitionRef { env, frame }.key().to_le_bytes());
                    out.extend_from_slice(&priority.to_le_bytes());
                }
            }
        }
        Some(out)
    }

    /// After a restore: the priorities a snapshot kept. Every transition the buffer holds enters at
    /// `max`, then takes its saved priority (keys the buffer no longer holds are skipped). The
    /// error names the first value that cannot be a priority of this buffer; nothing changes then.
    pub(crate) fn restore_priorities(&mut self, max: f64, saved: &[(u64, f64)]) -> std::result::Result<(), String> {
        let valid = |value: f64| value.is_finite() && value >= 0.0;
        if !valid(max) {
            return Err(format!("its largest priority is {max}, not a finite non-negative number"));
        }
        let num_envs = self.layout.num_envs;
        if let Some((index, (key, priority))) =
            saved.iter().enumerate().find(|(_, (key, priority))| TransitionRef::from_key(*key).env >= num_envs || !valid(*priority))
        {
            return Err(format!("entry {index} (key {key}, priority {priority}) is not a priority of this buffer's transitions"));
        }
        let mut priorities = self.every_transition_at(max);
        for &(key, priority) in saved {
            let transition = TransitionRef::from_key(key);
            let slot = self.slot(transition.env, transition.frame);
            if self.still_holds(transition) && priorities.get(slot).is_some() {
                priorities.update(slot, priority);
            }
        }
        self.priorities = Some(priorities);
        Ok(())
    }
}

/// Importance weights of a prioritized batch (Schaul et al. 2016, eq. 1): `(n * P(i))^-beta` for
/// `n` transitions that could be drawn, divided by the batch's largest so that they only scale
/// updates down (Acme's and Dopamine's normalisation; Schaul et al. divide by the buffer's
/// largest).
pub fn importance_weights(probabilities: &[f64], sampleable: usize, importance_exponent: f64, out: &mut Vec<f32>) {
    out.clear();
    out.extend(probabilities.iter().map(|&probability| (sampleable as f64 * probability).powf(-importance_exponent) as f32));
    let largest = out.iter().copied().fold(0.0f32, f32::max);
    if largest > 0.0 && largest.is_finite() {
        out.iter_mut().for_each(|weight| *weight /= largest);
    }
}

#[cfg(test)]
mod tests;
