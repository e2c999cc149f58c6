//! The asynchronous modes (`batch_size` below `num_envs`): EnvPool's, in one group, and the native
//! engine's, groups of `batch_size` envs each stepped whole; `async_reset`, `send`, `recv`, `send_recv`.

use std::sync::atomic::Ordering;
use std::task::Poll;

use futures_util::future::join_all;

use super::{copying, Session, StepOutcome};
use crate::actions::{check_mask, check_seed, validate_actions, ScatteredActions};
use crate::catalog::{async_batch, native_async_batch};
use crate::error::CoreError;
use crate::infos::Infos;
use crate::simulators::{SimulatorError, StepResult};
use crate::space::DType;

impl Session {
    /// The envs a `recv` returns at most, for a session in EnvPool's asynchronous mode (option
    /// `batch_size` below `num_envs`); None for a synchronous one.
    pub fn async_batch(&self) -> Option<usize> {
        async_batch(&self.config.options, self.config.num_envs)
    }

    pub(super) fn require_async(&self, what: &str) -> Result<usize, CoreError> {
        self.refuse_while_acting(what)?;
        self.async_batch().ok_or_else(|| {
            CoreError::InvalidSession(format!(
                "{what} is for sessions whose batch_size is below num_envs (EnvPool's asynchronous mode); this one \
                 steps every env at once (reset/step)"
            ))
        })
    }

    pub(super) fn require_sync(&self, what: &str) -> Result<(), CoreError> {
        self.refuse_while_acting(what)?;
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
    pub(super) fn steps_groups(&self) -> bool {
        native_async_batch(&self.config.options, self.config.num_envs).is_some()
    }

    /// Resets every env for `async_reset` (reseeded with the session's seeds when `seeded`).
    pub(super) async fn start_async_reset(&mut self, seeded: bool) -> Result<(), SimulatorError> {
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
    pub(super) async fn start_group_steps(&mut self, actions: &[u8], sent: &[bool]) {
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
    pub(super) async fn next_group(&mut self) -> (usize, Result<(Vec<bool>, StepResult), SimulatorError>) {
        if let Some((index, infos)) = self.group_resets.pop_front() {
            let n = self.groups[index].envs().len();
            let result = StepResult {
                rewards: vec![0.0; n],
                terminated: vec![false; n],
                truncated: vec![false; n],
                errors: Vec::new(),
                step_infos: Infos::default(),
                reset_infos: infos,
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
    pub(super) fn check_whole_groups(&self, sent: &[bool]) -> Result<(), CoreError> {
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

    pub(super) fn check_send(&self, dtype: DType, shape: &[usize], actions: &[u8], sent: &[bool]) -> Result<(), CoreError> {
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

    pub(super) fn mark_sent(&mut self, sent: &[bool]) {
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
        copying(self.step_copy_bytes(), || self.finish_recv(index, reply, started))
    }

    /// Refuses a recv that would wait forever: fewer than a batch stepping, counting `sending` envs
    /// about to be sent.
    pub(super) fn check_recv(&self, sending: usize) -> Result<(), CoreError> {
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
    pub(super) fn finish_recv(
        &mut self,
        index: usize,
        reply: Result<(Vec<bool>, StepResult), SimulatorError>,
        started: std::time::Instant,
    ) -> Result<(Vec<bool>, StepOutcome), CoreError> {
        let num_envs = self.num_envs();
        let envs = self.groups[index].envs();
        let (local_ready, result) = match reply {
            Ok((ready, result)) => {
                let problem = if ready.len() != envs.len()
                    || !ready.iter().zip(&self.in_flight[envs.clone()]).all(|(&ready, &stepping)| stepping || !ready)
                {
                    Some(format!(
                        "worker answered a recv with {} of {} envs ready, or an env that was not stepping",
                        ready.len(),
                        envs.len()
                    ))
                } else {
                    result.check(envs.len()).err()
                };
                if let Some(message) = problem {
                    self.needs_reset = true;
                    return Err(CoreError::Simulator(message));
                }
                (ready, result)
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
        outcome.step_infos.append(&result.step_infos, envs.start, |local| local_ready[local]);
        outcome.reset_infos.append(&result.reset_infos, envs.start, |local| local_ready[local]);
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
}
