//! The synchronous mode: reset (all envs or a mask, seeded) and step (all envs, or all but a mask).

use std::sync::atomic::Ordering;

use futures_util::future::join_all;
use radserve_replay::RecordedStep;

use super::{copying, ResetSpec, Session, StepOutcome};
use crate::infos::Infos;
use crate::actions::{check_mask, check_seed, validate_actions, MAX_SEED};
use crate::error::CoreError;
use crate::simulators::{SimulatorError, StepResult};
use crate::space::DType;

/// One group's part of a reset: its envs' seeds (if re-seeded) and mask (if partial).
type GroupReset = (Option<Vec<u64>>, Option<Vec<bool>>);

impl Session {
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
        self.reset_infos = Infos::default();
        for (index, result) in results.into_iter().enumerate() {
            let infos = match result {
                None => continue,
                Some(Ok(infos)) => self.checked_reset_infos(index, infos)?,
                Some(Err(SimulatorError::Lost(_))) => {
                    whole[index] = true;
                    self.reset_group(index).await?
                }
                Some(Err(error)) => return Err(error.into()),
            };
            self.reset_infos.append(&infos, self.groups[index].envs().start, |_| true);
        }
        Ok(copying(self.step_copy_bytes(), || self.take_reset(spec.mask.as_deref(), &plans, &whole)))
    }

    /// The groups a reset reset (`plans`, or `whole` where a lost group was reset whole) taken into
    /// the session: their stacks start from the first frames, the replay records those, their
    /// episode figures restart; returns every env's stacked observation through the view.
    fn take_reset(&mut self, mask: Option<&[bool]>, plans: &[Option<GroupReset>], whole: &[bool]) -> Vec<u8> {
        for index in 0..self.groups.len() {
            if plans[index].is_none() && !whole[index] {
                continue;
            }
            let mask = if whole[index] { None } else { mask };
            self.fill_stacks_from_current(index, mask);
            self.record_first_frames(index, self.step_calls, mask);
            for env in self.groups[index].envs().filter(|&env| mask.is_none_or(|mask| mask[env])) {
                self.episode_returns[env] = 0.0;
                self.episode_lengths[env] = 0;
            }
        }
        if mask.is_none() {
            self.needs_reset = false;
        }
        self.metrics.record_reset();
        self.viewed(&self.stacks)
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
        let copy_bytes = self.step_copy_bytes();
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
                Ok(result) => match result.check(group_len) {
                    Ok(()) => result,
                    Err(message) => {
                        self.needs_reset = true;
                        return Err(CoreError::Simulator(message));
                    }
                },
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
            copying(copy_bytes, || self.take_group_step(index, &result, actions, skip, &mut outcome));
        }
        let stepped = (0..num_envs).filter(|&env| !skipped(env)).count() as u64;
        copying(copy_bytes, || self.finish_step(stepped, started, &mut outcome));
        Ok(outcome)
    }

    /// Group `index`'s answer to a step taken into the session: its envs' infos, the transitions
    /// recorded into the replay (before the stacks move on), and each stepped env's stack, reward
    /// and episode moved on. Synchronous, so that no lock is held across an await.
    fn take_group_step(&mut self, index: usize, result: &StepResult, actions: &[u8], skip: Option<&[bool]>, outcome: &mut StepOutcome) {
        let skipped = |env: usize| skip.is_some_and(|skip| skip[env]);
        let action_bytes = self.frame_spec.action.num_bytes();
        let group_envs = self.groups[index].envs();
        outcome.step_infos.append(&result.step_infos, group_envs.start, |local| !skipped(group_envs.start + local));
        outcome.reset_infos.append(&result.reset_infos, group_envs.start, |local| !skipped(group_envs.start + local));
        if let Some(replay) = &self.replay {
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
                        acted: self.acted().map(|acted| acted.by(env)),
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
                self.advance(index, local, env, result, outcome);
            }
        }
    }
}
