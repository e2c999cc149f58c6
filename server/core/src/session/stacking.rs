//! Frame stacking in the server: each env's stack moves on by one frame per step (or restarts at an
//! episode's first frame), the replay records first frames, and observations leave through the view.

use std::sync::atomic::Ordering;

use radserve_augment::{Augmentation, Draws, FrameShape, ImagePlan, Pipeline};

use super::{Session, StepOutcome};
use crate::error::CoreError;
use crate::simulators::StepResult;
use crate::space::{DType, Space};

impl Session {
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
    pub(super) fn viewed(&self, stacks: &[u8]) -> Vec<u8> {
        let Some(view) = &self.view else { return stacks.to_vec() };
        let samples = stacks.len() / view.input_shape().sample_len();
        let mut out = vec![0; samples * view.output_shape().sample_len()];
        view.apply(stacks, &mut out, &Draws::new(0)).expect("buffers sized from the plan");
        out
    }

    /// Record each env of group `index` (those `mask` marks, if given) starting an episode at its
    /// current frame, before the Step call `step_index`.
    pub(super) fn record_first_frames(&self, index: usize, step_index: u64, mask: Option<&[bool]>) {
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

    pub(super) fn stack_bytes(&self) -> usize {
        self.config.frame_stack * self.layout.frame_bytes
    }

    /// What a step of every env copies at least once: each env's stack (see `copying`).
    pub(super) fn step_copy_bytes(&self) -> usize {
        self.num_envs() * self.stack_bytes()
    }

    /// Sets each stack of a group (those `mask` marks, if given) to its env's current frame
    /// repeated (the stacking at reset).
    pub(super) fn fill_stacks_from_current(&mut self, index: usize, mask: Option<&[bool]>) {
        let stack_bytes = self.stack_bytes();
        let group = &self.groups[index];
        for (local, env) in group.envs().enumerate() {
            if mask.is_some_and(|mask| !mask[env]) {
                continue;
            }
            fill_stack(&mut self.stacks[env * stack_bytes..][..stack_bytes], &group.frames()[self.layout.frame(local)]);
        }
    }

    /// After a step or recv that stepped `stepped` envs since `started`: the counters and metrics, and
    /// the outcome's observations through the view.
    pub(super) fn finish_step(&mut self, stepped: u64, started: std::time::Instant, outcome: &mut StepOutcome) {
        self.stats.total_env_steps.fetch_add(stepped, Ordering::Relaxed);
        let errors = outcome.episodes.iter().filter(|episode| episode.error.is_some()).count() as u64;
        self.metrics.record_step(self.config.env.family, stepped, started.elapsed(), outcome.episodes.len() as u64, errors);
        self.step_calls += 1;
        outcome.obs = self.viewed(&self.stacks);
        outcome.final_obs = self.viewed(&outcome.final_obs);
    }

    /// Env `env` (group `index`'s env `local`) took a step with `result`'s entry `local`: its reward and
    /// flags go into `outcome`, its stack moves on to its new frame, and when its episode ended the
    /// episode's last stacked observation goes into `outcome.final_obs` and the stack restarts from
    /// the next episode's first frame (same-step autoreset).
    pub(super) fn advance(&mut self, index: usize, local: usize, env: usize, result: &StepResult, outcome: &mut StepOutcome) {
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
}

/// Sets every slot of a stack to `frame` (a stack at its episode's first frame).
pub(super) fn fill_stack(stack: &mut [u8], frame: &[u8]) {
    for slot in stack.chunks_exact_mut(frame.len()) {
        slot.copy_from_slice(frame);
    }
}

/// Drops the oldest frame of a stack and appends `frame`.
pub(super) fn push_frame(stack: &mut [u8], frame: &[u8]) {
    stack.copy_within(frame.len().., 0);
    let tail = stack.len() - frame.len();
    stack[tail..].copy_from_slice(frame);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stacks_shift_oldest_out() {
        let mut stack = vec![1, 1, 2, 2, 3, 3];
        push_frame(&mut stack, &[4, 4]);
        assert_eq!(stack, vec![2, 2, 3, 3, 4, 4]);
        let mut single = vec![7, 7];
        push_frame(&mut single, &[8, 8]);
        assert_eq!(single, vec![8, 8]);
    }
}
