//! What the core needs of simulators, as a trait: the worker processes implement it (`radserve-sim`),
//! and so does a fake in tests ([`crate::fake`]), so that sessions, stacking, autoreset, replay
//! recording and recovery from a lost worker are tested without Python.
//!
//! A session's environments live in groups, each hosted by one simulator process. A group writes
//! each env's current frame (and, in the step that ends an episode, the episode's last frame) into
//! memory the core reads after the call returns ([`FrameLayout`]); everything else comes back as a
//! [`StepResult`].

use std::future::Future;
use std::ops::Range;
use std::pin::Pin;

use async_trait::async_trait;
use serde::{Deserialize, Serialize};

use crate::catalog::{EnvId, EnvNames, Options};
use crate::infos::Infos;
use crate::space::Space;

/// What one environment observes (one frame, before stacking) and how it is acted on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EnvSpec {
    pub observation: Space,
    pub action: Space,
}

/// A group's answer to a step.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepResult {
    pub rewards: Vec<f64>,
    pub terminated: Vec<bool>,
    pub truncated: Vec<bool>,
    /// (index within the group, message) for each env whose simulator raised during this step; that
    /// env's episode ends as truncated and it starts a new one.
    pub errors: Vec<(u32, String)>,
    /// The envs' own info dicts (gymnasium's `info`) from the step, of the envs that returned a
    /// non-empty one.
    pub step_infos: Infos,
    /// The info dicts of the resets the group made in the step, of the envs whose episode ended
    /// (same-step autoreset) or whose simulator raised.
    pub reset_infos: Infos,
}

impl StepResult {
    /// Whether this result has one entry per environment of a group of `envs`, and infos of those
    /// envs only: what is wrong with it, else.
    pub fn check(&self, envs: usize) -> Result<(), String> {
        if self.rewards.len() != envs || self.terminated.len() != envs || self.truncated.len() != envs {
            return Err(format!(
                "worker answered a step of {envs} envs with {} rewards, {} terminated and {} truncated flags",
                self.rewards.len(),
                self.terminated.len(),
                self.truncated.len()
            ));
        }
        self.step_infos.check(envs).and_then(|()| self.reset_infos.check(envs)).map_err(|error| format!("worker answered a step with a bad info: {error}"))
    }
}

/// Where environment `index` of a group keeps its frames in the group's frame memory: its current
/// frame, then the last frame of its previous episode (written only in the step that ends one).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameLayout {
    pub frame_bytes: usize,
}

impl FrameLayout {
    pub fn memory_len(&self, num_envs: usize) -> usize {
        2 * self.frame_bytes * num_envs
    }

    pub fn frame(&self, index: usize) -> Range<usize> {
        let start = 2 * self.frame_bytes * index;
        start..start + self.frame_bytes
    }

    pub fn final_frame(&self, index: usize) -> Range<usize> {
        let start = 2 * self.frame_bytes * index + self.frame_bytes;
        start..start + self.frame_bytes
    }
}

/// A group's step started by [`EnvGroup::start_step`]: resolves to its result.
pub type PendingStep = Pin<Box<dyn Future<Output = Result<StepResult, SimulatorError>> + Send>>;

/// Why a simulator call did not do what was asked.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SimulatorError {
    /// The simulator would not build the environments with these options (the caller's mistake).
    #[error("{0}")]
    Refused(String),
    /// The simulator raised, or answered something that does not fit the request: the call failed,
    /// and the group's envs are in an unknown state.
    #[error("{0}")]
    Failed(String),
    /// The process hosting the group died or hung and was replaced: the group's envs were rebuilt,
    /// not reset, and whatever episode they were in is over.
    #[error("{0}")]
    Lost(String),
    /// No simulator process could be started or reached.
    #[error("{0}")]
    Unavailable(String),
    /// The host is out of memory or file descriptors for the group's frame memory.
    #[error("{0}")]
    OutOfResources(String),
}

/// One group of a session's environments, in one simulator process.
#[async_trait]
pub trait EnvGroup: Send + Sync {
    /// The session's environments this group hosts.
    fn envs(&self) -> Range<usize>;

    /// The group's frames, laid out by [`FrameLayout`]; what the last reset or step wrote.
    fn frames(&self) -> &[u8];

    /// Resets every env of the group, or those `mask` marks (one entry per env of the group),
    /// reseeding env j with `seeds[j]` when given. After [`SimulatorError::Lost`], the group is
    /// usable again once a full reset succeeds.
    async fn reset(&mut self, seeds: Option<Vec<u64>>, mask: Option<Vec<bool>>) -> Result<Infos, SimulatorError>;

    /// Steps every env of the group with `actions` (the group's envs' actions, little-endian bytes of
    /// the action dtype, already checked against the action space), except those `skip` marks: they
    /// keep their frame and report reward 0 and no episode end.
    async fn step(&mut self, actions: Vec<u8>, skip: Option<Vec<bool>>) -> Result<StepResult, SimulatorError>;

    /// Starts a step of every env of the group with `actions` (as `step`'s) and returns what resolves
    /// to its result, without waiting for it: the native engine's asynchronous mode keeps one group's
    /// step in flight while the session reads another's. Dropping it drops the result, not the step.
    /// By default the step is taken here and the result is ready at once.
    async fn start_step(&mut self, actions: Vec<u8>) -> PendingStep {
        let result = self.step(actions, None).await;
        Box::pin(std::future::ready(result))
    }

    /// EnvPool's asynchronous mode, for a group built with a `batch_size` below its envs: resets every
    /// env (reseeding env j with `seeds[j]` when given); their first frames come back through `recv`.
    async fn async_reset(&mut self, seeds: Option<Vec<u64>>) -> Result<(), SimulatorError> {
        let _ = seeds;
        Err(SimulatorError::Refused("these simulators have no asynchronous mode".into()))
    }

    /// Starts the next step of the envs `sent` marks (one entry per env of the group) with their rows of
    /// `actions` (every env's row, as in `step`; the others are ignored), and returns without waiting.
    async fn send(&mut self, actions: Vec<u8>, sent: Vec<bool>) -> Result<(), SimulatorError> {
        let _ = (actions, sent);
        Err(SimulatorError::Refused("these simulators have no asynchronous mode".into()))
    }

    /// Waits for the next batch of envs whose step (or reset) is complete: which envs (`ready`, one
    /// entry per env of the group) and their results, laid out as `step`'s (the other envs' entries
    /// are zero). A ready env whose episode ended has its last frame in the final-frame slot.
    async fn recv(&mut self) -> Result<(Vec<bool>, StepResult), SimulatorError> {
        Err(SimulatorError::Refused("these simulators have no asynchronous mode".into()))
    }

    /// `send` then `recv` (EnvPool's `step(action, env_id)`); simulators in another process do both in
    /// one round trip.
    async fn send_recv(&mut self, actions: Vec<u8>, sent: Vec<bool>) -> Result<(Vec<bool>, StepResult), SimulatorError> {
        self.send(actions, sent).await?;
        self.recv().await
    }

    /// Releases the envs. The group is not used afterwards.
    async fn close(&mut self);
}

/// The simulators a server hosts its environments in.
#[async_trait]
pub trait Simulators: Send + Sync + 'static {
    /// How many simulator processes there are (the default memory budget leaves room for each).
    fn processes(&self) -> usize;

    /// Every environment id the simulators can host.
    async fn env_names(&self) -> Result<EnvNames, SimulatorError>;

    /// The processes (by index) whose current reset, step or close has run longer than `after`: a
    /// stuck worker, seen before its call deadline kills it (health reports NOT_SERVING meanwhile).
    fn overdue(&self, after: std::time::Duration) -> Vec<usize>;

    /// The spec of each environment with its (resolved, server-side options removed) options, or why
    /// it could not be built.
    async fn env_specs(&self, envs: Vec<(EnvId, Options)>) -> Result<Vec<Result<EnvSpec, String>>, SimulatorError>;

    /// Builds `seeds.len()` environments of `env`, env i seeded `seeds[i]`, in groups that cover
    /// `0..seeds.len()` in order. On error nothing stays built.
    async fn create_groups(
        &self,
        env: &EnvId,
        options: &Options,
        seeds: Vec<u64>,
    ) -> Result<(EnvSpec, Vec<Box<dyn EnvGroup>>), SimulatorError>;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_and_final_frames_do_not_overlap() {
        let layout = FrameLayout { frame_bytes: 10 };
        assert_eq!(layout.frame(1), 20..30);
        assert_eq!(layout.final_frame(1), 30..40);
        assert_eq!(layout.memory_len(2), 40);
    }
}
