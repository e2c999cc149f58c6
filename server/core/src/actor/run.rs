//! The actor's loop: one task per session, stepping every env at once with the newest policy,
//! within the request's rate and Reverb's limiter, until stopped, done or failed.

use std::sync::atomic::Ordering;
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

use radserve_replay::{RateLimiter, ReplayBuffer};
use rand_chacha::ChaCha8Rng;
use tokio::sync::watch;
use tracing::{info, warn};

use super::{action_spec, ActingRequest, ActingState, ActorSlot, HeldPolicy, MAX_FAILED_STEPS, RECENT_EPISODES};
use crate::error::CoreError;
use crate::manager::SharedSession;
use crate::metrics::CoreMetrics;
use crate::principal::log_id;
use crate::session::ActedStamp;

/// An actor about to run: the session it was handed, and how it acts.
pub(crate) struct Actor {
    pub(crate) session: SharedSession,
    pub(crate) slot: Arc<ActorSlot>,
    pub(crate) replay: Option<Arc<RwLock<ReplayBuffer>>>,
    pub(crate) limiter: Option<RateLimiter>,
    pub(crate) request: ActingRequest,
    pub(crate) rng: ChaCha8Rng,
    pub(crate) metrics: Arc<CoreMetrics>,
    pub(crate) session_id: String,
    /// Turns true when the session is closed.
    pub(crate) closed: watch::Receiver<bool>,
}

/// Why an actor loop ended.
enum Ended {
    Stopped,
    Done,
    Failed(String),
}

/// The signals that end a wait: StopActing, or the session closed.
struct Signals {
    stopped: watch::Receiver<bool>,
    closed: watch::Receiver<bool>,
}

impl Signals {
    fn any(&self) -> bool {
        *self.stopped.borrow() || *self.closed.borrow()
    }

    /// Runs `wait` unless a signal comes first: false when one did.
    async fn unless_stopped(&mut self, wait: impl std::future::Future<Output = ()>) -> bool {
        tokio::select! {
            _ = self.stopped.wait_for(|stop| *stop) => false,
            _ = self.closed.wait_for(|closed| *closed) => false,
            () = wait => true,
        }
    }
}

impl Actor {
    /// Acts until stopped, done or failed, then gives the session back to its clients. The loop runs
    /// in a task of its own, so that even a panic in it (a bug) ends as a failed actor whose session
    /// is usable again, never as a session refused for ever.
    pub(crate) async fn run(self, policy: HeldPolicy, stopped: watch::Receiver<bool>) {
        let (session, slot, metrics, session_id) = (self.session.clone(), self.slot.clone(), self.metrics.clone(), self.session_id.clone());
        let ended = match tokio::spawn(self.act_owned(policy, stopped)).await {
            Ok((ended, policy)) => {
                // A policy whose runtime was stopped (past its memory or time) is dropped, its
                // charge returned: StartActing then asks for a new one rather than failing again.
                if policy.policy.usable() {
                    slot.give_back(policy);
                }
                ended
            }
            Err(error) => Ended::Failed(format!("the actor stopped on an internal error: {error}")),
        };
        session.lock().await.hand_back();
        Self::record_end(&slot, &metrics, &session_id, ended);
    }

    async fn act_owned(mut self, mut policy: HeldPolicy, stopped: watch::Receiver<bool>) -> (Ended, HeldPolicy) {
        let mut signals = Signals { stopped, closed: self.closed.clone() };
        let ended = self.act(&mut policy, &mut signals).await;
        (ended, policy)
    }

    fn record_end(slot: &ActorSlot, metrics: &CoreMetrics, session_id: &str, ended: Ended) {
        let (state, error) = match ended {
            Ended::Stopped | Ended::Done => (ActingState::Stopped, None),
            Ended::Failed(message) => {
                warn!(session = log_id(session_id), error = %message, "acting failed");
                metrics.acting.failures.fetch_add(1, Ordering::Relaxed);
                (ActingState::Failed, Some(message))
            }
        };
        slot.update(|status| {
            status.state = state;
            if error.is_some() {
                status.error = error;
            }
        });
        info!(session = log_id(session_id), state = state.name(), "acting ended");
    }

    /// A reset or step of the envs failed: the actor goes on (the error shown) until it is the
    /// `MAX_FAILED_STEPS`th in a row, which ends it.
    fn envs_failed(&self, failures: &mut u32, error: &CoreError) -> Option<Ended> {
        *failures += 1;
        if *failures >= MAX_FAILED_STEPS {
            return Some(Ended::Failed(format!("the envs failed {failures} times in a row; the last: {error}")));
        }
        self.slot.update(|status| status.error = Some(error.to_string()));
        None
    }

    /// Waits until the rate limiter lets `count` inserts through, woken by the buffer's samples:
    /// false when stopped meanwhile.
    async fn until_insert_allowed(&self, count: u64, signals: &mut Signals) -> bool {
        let (Some(limiter), Some(replay)) = (&self.limiter, &self.replay) else { return true };
        let allowed = || limiter.can_insert(replay.read().expect("replay lock").occupancy(), count);
        if allowed() {
            return true;
        }
        let activity = replay.read().expect("replay lock").activity();
        signals.unless_stopped(activity.wait(allowed)).await
    }

    async fn act(&mut self, policy: &mut HeldPolicy, signals: &mut Signals) -> Ended {
        let (num_envs, action_space) = {
            let session = self.session.lock().await;
            (session.num_envs() as u64, session.frame_spec.action.clone())
        };
        let Ok(actions_spec) = action_spec(&action_space) else { return Ended::Failed("the action space is not one a policy acts in".into()) };
        let mut next_at = tokio::time::Instant::now();
        let mut failures = 0;
        let (mut env_steps, mut episodes) = (0u64, 0u64);
        loop {
            if signals.any() {
                return Ended::Stopped;
            }
            if self.request.max_episodes.is_some_and(|max| episodes >= max) || self.request.max_env_steps.is_some_and(|max| env_steps >= max) {
                return Ended::Done;
            }
            if let Some(rate) = self.request.steps_per_second {
                if !signals.unless_stopped(tokio::time::sleep_until(next_at)).await {
                    return Ended::Stopped;
                }
                next_at = next_at.max(tokio::time::Instant::now() - Duration::from_secs(1)) + Duration::from_secs_f64(num_envs as f64 / rate);
            }
            let limited_from = Instant::now();
            if !self.until_insert_allowed(num_envs, signals).await {
                return Ended::Stopped;
            }
            let limited = limited_from.elapsed().as_secs_f64();
            if let Some(newer) = self.slot.take_pending() {
                *policy = newer;
            }
            let mut session = self.session.lock().await;
            let started = Instant::now();
            if session.needs_reset() {
                if let Err(error) = session.reset_as_actor().await {
                    if let Some(ended) = self.envs_failed(&mut failures, &error) {
                        return ended;
                    }
                    continue;
                }
            }
            let obs = session.current_observations();
            let inference_started = Instant::now();
            let random = env_steps < self.request.random_steps;
            let (actions, stamp) = if random {
                (actions_spec.random(num_envs as usize, &mut self.rng), None)
            } else {
                let total = session.total_env_steps();
                match policy.policy.act(&obs, &mut self.rng, total, self.request.eval).await {
                    Ok(acted) => {
                        let stamp = ActedStamp { version: policy.version as i32, log_prob: acted.log_prob, value: acted.value };
                        (acted.actions, Some(stamp))
                    }
                    Err(error) => return Ended::Failed(error.to_string()),
                }
            };
            let inference = if random { 0.0 } else { inference_started.elapsed().as_secs_f64() };
            let version = stamp.as_ref().map(|stamp| stamp.version as u32);
            let shape: Vec<usize> = std::iter::once(num_envs as usize).chain(action_space.shape().iter().copied()).collect();
            let outcome = session.step_as_actor(action_space.dtype(), &shape, &actions, stamp).await;
            drop(session);
            let step_seconds = started.elapsed().as_secs_f64() - inference;
            match outcome {
                Ok(outcome) => {
                    failures = 0;
                    env_steps += num_envs;
                    episodes += outcome.episodes.len() as u64;
                    self.metrics.acting.env_steps.fetch_add(num_envs, Ordering::Relaxed);
                    self.metrics.acting.add_inference(inference);
                    self.slot.update(|status| {
                        status.env_steps = env_steps;
                        status.episodes = episodes;
                        if version.is_some() {
                            status.acting_version = version;
                        }
                        status.inference_seconds += inference;
                        status.step_seconds += step_seconds;
                        status.limited_seconds += limited;
                        status.recent_returns.extend(outcome.episodes.iter().map(|episode| episode.episode_return));
                        status.recent_envs.extend(outcome.episodes.iter().map(|episode| episode.env_index as u32));
                        let old = status.recent_returns.len().saturating_sub(RECENT_EPISODES);
                        status.recent_returns.drain(..old);
                        status.recent_envs.drain(..old);
                    });
                }
                Err(error) => {
                    if let Some(ended) = self.envs_failed(&mut failures, &error) {
                        return ended;
                    }
                }
            }
        }
    }
}
