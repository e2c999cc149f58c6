//! One env of a session acted alone, the others left as they are (dm_env_rpc's JoinWorld binds a
//! stream to one env): its observation, a new episode in it, a step of it with the others skipped.

use super::{ResetSpec, Session};
use crate::error::CoreError;

/// What a step of one env returned.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvStep {
    pub reward: f64,
    /// Its observation after the step: the next episode's first when the step ended one.
    pub observation: Vec<u8>,
    /// Set when the step ended its episode.
    pub ended: Option<EnvEnd>,
}

/// How one env's episode ended.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvEnd {
    /// True for a terminal state; false for a truncation (a time limit, a simulator error).
    pub terminated: bool,
    /// The episode's last observation.
    pub last_observation: Vec<u8>,
}

impl Session {
    /// Env `env`'s observation now (through the view), None before the session's first reset.
    pub fn env_observation(&self, env: usize) -> Option<Vec<u8>> {
        (!self.needs_reset && env < self.num_envs()).then(|| self.env_view(env))
    }

    /// Env `env`'s observation; a session never reset (or whose last step failed) is reset whole
    /// first, env i seeded `seed + i` as a session's first reset is.
    pub async fn current_env_observation(&mut self, env: usize) -> Result<Vec<u8>, CoreError> {
        self.check_env(env)?;
        if self.needs_reset {
            self.reset_with(&ResetSpec::default()).await?;
        }
        Ok(self.env_view(env))
    }

    /// Starts a new episode in env `env` and returns its first observation. Seeded: reset with that
    /// seed. Unseeded, an env that has not stepped since its last reset is already at an episode's
    /// start and stays there (so a session's first episodes are its seed's, whether or not a new
    /// one is asked for before the first step); otherwise its random stream continues.
    pub async fn reset_env(&mut self, env: usize, seed: Option<u64>) -> Result<Vec<u8>, CoreError> {
        self.refuse_while_acting("reset")?;
        self.check_env(env)?;
        let fresh = self.needs_reset || self.episode_lengths[env] == 0;
        if seed.is_none() && fresh {
            return self.current_env_observation(env).await;
        }
        if self.needs_reset {
            self.reset_with(&ResetSpec::default()).await?;
        }
        let num_envs = self.num_envs();
        let mut mask = vec![false; num_envs];
        mask[env] = true;
        let env_seeds = seed.map(|seed| vec![seed; num_envs]);
        self.reset_with(&ResetSpec { seed: None, env_seeds, mask: Some(mask) }).await?;
        Ok(self.env_view(env))
    }

    /// Steps env `env` alone with `action` (one env's action); every other env is skipped.
    pub async fn step_env(&mut self, env: usize, action: &[u8]) -> Result<EnvStep, CoreError> {
        self.refuse_while_acting("step")?;
        self.check_env(env)?;
        let num_envs = self.num_envs();
        // Every env gets the same (checked) action; all but `env` are skipped.
        let actions = action.repeat(num_envs);
        let mut shape = vec![num_envs];
        shape.extend_from_slice(self.frame_spec.action.shape());
        let skip: Vec<bool> = (0..num_envs).map(|other| other != env).collect();
        let outcome = self.step_except(self.frame_spec.action.dtype(), &shape, &actions, Some(&skip)).await?;
        let ended = outcome.episodes.iter().position(|episode| episode.env_index == env).map(|position| EnvEnd {
            terminated: outcome.episodes[position].terminated,
            last_observation: row(&outcome.final_obs, position, outcome.episodes.len()).to_vec(),
        });
        Ok(EnvStep { reward: outcome.rewards[env], observation: row(&outcome.obs, env, num_envs).to_vec(), ended })
    }

    fn check_env(&self, env: usize) -> Result<(), CoreError> {
        if env >= self.num_envs() {
            return Err(CoreError::InvalidSession(format!(
                "env {env} is out of range: the session has {} envs",
                self.num_envs()
            )));
        }
        Ok(())
    }

    /// Env `env`'s stack now, through the view.
    fn env_view(&self, env: usize) -> Vec<u8> {
        let stack_bytes = self.stack_bytes();
        self.viewed(&self.stacks[env * stack_bytes..][..stack_bytes])
    }
}

/// Row `index` of `rows` equal rows.
fn row(data: &[u8], index: usize, rows: usize) -> &[u8] {
    let len = data.len() / rows.max(1);
    &data[index * len..(index + 1) * len]
}
