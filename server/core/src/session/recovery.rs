//! A group whose simulator process was lost (died, hung, or replaced for another session): it is
//! rebuilt from its envs' seeds and its episodes end, truncated, with the error.

use super::{Session, StepOutcome};
use crate::error::CoreError;
use crate::infos::Infos;

impl Session {
    /// Resets one group with its envs' seeds (after its process was replaced); its reset infos.
    pub(super) async fn reset_group(&mut self, index: usize) -> Result<Infos, CoreError> {
        let seeds = self.group_seeds(index);
        let infos = self.groups[index].reset(Some(seeds), None).await?;
        self.checked_reset_infos(index, infos)
    }

    /// Group `index`'s reset infos, refused when a column does not fit the group (nothing of a
    /// worker's answer is taken before it is checked).
    pub(super) fn checked_reset_infos(&self, index: usize, infos: Infos) -> Result<Infos, CoreError> {
        infos.check(self.groups[index].envs().len()).map_err(|error| CoreError::Simulator(format!("worker answered a reset with a bad info: {error}")))?;
        Ok(infos)
    }

    /// After a group's process was lost mid-step: its envs' episodes end as truncated with the error,
    /// their last observation is the stack before the step, and they start again from a reset.
    pub(super) async fn recover_lost_group(
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
        outcome.reset_infos.append(&infos, self.groups[index].envs().start, |_| true);
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
}
