//! Creating a session under the server's limits, each principal's and the memory budget: every
//! share is taken before anything is built and given back if the session is not registered.

use std::sync::Arc;
use std::time::Instant;

use tokio::sync::Mutex;
use tracing::info;

use super::lease::{elapsed_ms, Lease};
use super::{describe, BufferRequest, Entry, SessionExtras, SessionInfo, SessionManager};
use crate::actions::check_seed;
use crate::bounds;
use crate::budget::{self, MemoryBudget, Reservation};
use crate::catalog::{self, OptionValue, Options, FRAME_STACK};
use crate::error::CoreError;
use crate::principal::{log_id, Principal};
use crate::session::{Session, SessionConfig};

impl SessionManager {
    pub async fn create_session(
        &self,
        caller: &Principal,
        env_id: &str,
        num_envs: usize,
        seed: u64,
        overrides: &Options,
        extras: &SessionExtras,
    ) -> Result<SessionInfo, CoreError> {
        if num_envs == 0 {
            return Err(CoreError::InvalidSession("num_envs must be at least 1".into()));
        }
        if num_envs > self.limits.max_envs_per_session {
            return Err(CoreError::TooLarge(format!(
                "num_envs {num_envs} exceeds this server's limit of {} environments per session",
                self.limits.max_envs_per_session
            )));
        }
        check_seed(seed, num_envs)?;
        bounds::check_len("env_id", env_id, bounds::MAX_ID_BYTES)?;
        if let Some(view) = &extras.observation_view {
            bounds::check_len("observation_view", view, radserve_augment::MAX_PIPELINE_TEXT_BYTES)?;
        }
        if let Some(buffer) = extras.buffer {
            self.precheck_buffer(buffer, num_envs)?;
        }
        if let Some(name) = &extras.name {
            super::snapshots::check_name(name)?;
        }
        let env = self.names().await?.parse(env_id)?;
        let options = catalog::resolve_options(&env, overrides)?;
        let frame_stack = options[FRAME_STACK].as_int().unwrap_or(1) as usize;
        check_batch_size(&options, num_envs, extras)?;

        // Before anything is built: the envs' own memory at their family's measured cost.
        let per_env = budget::env_cost_bytes(&env, &options);
        let quota = self.quota(caller);
        let envs_memory = self.budget.try_reserve_within(
            quota.as_ref(),
            per_env.saturating_mul(num_envs as u64),
            &format!("{num_envs} envs of {} (~{} each)", env.full(), budget::human(per_env)),
        )?;
        let place = self.reserve(caller, num_envs)?;
        let name = match &extras.name {
            Some(name) => Some(self.hold_name(&place.owner, name)?),
            None => None,
        };
        let config = SessionConfig { env, num_envs, seed, options, frame_stack };
        let mut session = Session::create(self.simulators.as_ref(), config).await?.with_metrics(self.metrics.clone());
        let prepared = match &extras.observation_view {
            Some(view) => session.set_view(view),
            None => Ok(()),
        };
        let prepared = prepared.and_then(|()| check_observation_bytes(&session));
        let prepared = prepared.and_then(|()| {
            let frames = self.budget.try_reserve_within(
                quota.as_ref(),
                frame_buffer_bytes(&session),
                &format!("the frame buffers of {num_envs} envs"),
            )?;
            let replay = match extras.buffer {
                Some(buffer) => Some(self.attach_replay(&mut session, buffer, quota.as_ref())?),
                None => None,
            };
            Ok((frames, replay))
        });
        let (memory, replay_share) = match prepared {
            Ok((frames, Some((replay, share)))) => (vec![envs_memory, frames, replay], Some(share)),
            Ok((frames, None)) => (vec![envs_memory, frames], None),
            Err(error) => {
                session.close().await;
                return Err(error);
            }
        };
        let snapshot = match &name {
            Some(name) => match self.open_snapshot(&mut session, &place.owner, &name.name).await {
                Ok(snapshot) => snapshot,
                Err(error) => {
                    session.close().await;
                    return Err(error);
                }
            },
            None => None,
        };
        let session_id = self.new_session_id();
        let mut info = describe(&session_id, &session);
        info.name = extras.name.clone();
        if let (Some(replay_info), Some(snapshot), Some(replay)) = (info.replay.as_mut(), &snapshot, session.replay()) {
            replay_info.snapshot = Some(snapshot.info(replay));
        }
        let (stats, replay) = (session.stats.clone(), session.replay().cloned());
        let shared = Arc::new(Mutex::new(session));
        let registered = {
            let mut registry = self.sessions.lock().expect("registry lock");
            if registry.closing {
                false
            } else {
                let entry = Entry {
                    session: shared.clone(),
                    owner: place.owner.clone(),
                    memory,
                    info: info.clone(),
                    stats,
                    replay,
                    lease: Arc::new(Lease::new(elapsed_ms(self.clock))),
                    created: Instant::now(),
                    name: extras.name.clone(),
                    snapshot,
                    actor: Arc::default(),
                };
                registry.sessions.insert(session_id.clone(), entry);
                true
            }
        };
        if !registered {
            // The place and the replay share go back as they drop.
            shared.lock().await.close().await;
            return Err(CoreError::ShuttingDown);
        }
        // Registered: from here the entry holds them, and close_entry gives them back.
        let owner = place.keep();
        if let Some(share) = replay_share {
            share.keep();
        }
        if let Some(name) = name {
            name.keep();
        }
        info!(session = log_id(&session_id), owner = %owner, env = %info.env_id, envs = num_envs, seed, "session created");
        Ok(info)
    }

    /// The memory quota of `caller`, if it has one (made on first use, then shared by its sessions).
    pub(super) fn quota(&self, caller: &Principal) -> Option<Arc<MemoryBudget>> {
        let limit = caller.limits().memory_bytes?;
        let mut registry = self.sessions.lock().expect("registry lock");
        let usage = registry.principals.entry(caller.shared_name()).or_default();
        Some(usage.quota.get_or_insert_with(|| MemoryBudget::quota(limit, caller.shared_name())).clone())
    }

    /// Counts a session of `num_envs` envs against the server's and `caller`'s limits; the place is
    /// given back when the returned guard drops, unless it is kept.
    pub(super) fn reserve(&self, caller: &Principal, num_envs: usize) -> Result<Place<'_>, CoreError> {
        let mut registry = self.sessions.lock().expect("registry lock");
        if registry.closing {
            return Err(CoreError::ShuttingDown);
        }
        let name = caller.shared_name();
        let (sessions, envs) = registry.principals.get(&name).map_or((0, 0), |usage| (usage.sessions, usage.envs));
        if let Some(max) = caller.limits().max_sessions.filter(|&max| sessions >= max) {
            return Err(CoreError::OverLimit(format!(
                "principal '{name}' already has {sessions} sessions open, its limit of {max} (max_sessions in its \
                 tokens file entry); close one first"
            )));
        }
        if let Some(max) = caller.limits().max_envs.filter(|&max| envs + num_envs > max) {
            return Err(CoreError::over_limit(num_envs > max, format!(
                "{num_envs} more environments would give principal '{name}' {}, above its limit of {max} (max_envs \
                 in its tokens file entry)",
                envs + num_envs
            )));
        }
        if registry.reserved_sessions >= self.limits.max_sessions {
            return Err(CoreError::OverLimit(format!(
                "this server already hosts {} sessions, its limit; close one first",
                registry.reserved_sessions
            )));
        }
        if registry.reserved_envs + num_envs > self.limits.max_total_envs {
            return Err(CoreError::over_limit(num_envs > self.limits.max_total_envs, format!(
                "{num_envs} more environments would make {} on this server, above its limit of {}",
                registry.reserved_envs + num_envs,
                self.limits.max_total_envs
            )));
        }
        registry.reserved_envs += num_envs;
        registry.reserved_sessions += 1;
        let usage = registry.principals.entry(name.clone()).or_default();
        usage.envs += num_envs;
        usage.sessions += 1;
        Ok(Place { manager: self, owner: name, num_envs, kept: false })
    }

    /// Takes `name` among `owner`'s session names until the returned guard drops (unless kept: then
    /// until the session closes).
    fn hold_name(&self, owner: &Arc<str>, name: &str) -> Result<NameHold<'_>, CoreError> {
        let mut registry = self.sessions.lock().expect("registry lock");
        if !registry.names.insert((owner.clone(), name.to_string())) {
            let live = registry
                .sessions
                .iter()
                .find(|(_, entry)| entry.owner == *owner && entry.name.as_deref() == Some(name))
                .map_or_else(|| "is being created".to_string(), |(id, _)| format!("is session {id}"));
            return Err(CoreError::NameTaken(format!(
                "principal '{owner}' already has a session named '{name}' (it {live}): close it first, or use it"
            )));
        }
        Ok(NameHold { manager: self, owner: owner.clone(), name: name.to_string(), kept: false })
    }

    /// What can be known of a buffer before any environment is built (its frame size comes from the
    /// simulator): a capacity in range, and at least the bookkeeping bytes of every transition within
    /// the replay budget. The exact size is checked again once the frames are known.
    pub(super) fn precheck_buffer(&self, buffer: BufferRequest, num_envs: usize) -> Result<(), CoreError> {
        let capacity = match buffer {
            BufferRequest::Replay { capacity } => capacity,
            BufferRequest::Rollout { steps } => steps.saturating_mul(num_envs),
        };
        radserve_replay::check_capacity(capacity)?;
        let least = (capacity as u64).saturating_mul(radserve_replay::MIN_BYTES_PER_TRANSITION as u64);
        let budget = self.limits.replay_memory_bytes;
        if least > budget {
            return Err(CoreError::TooLarge(format!(
                "a replay buffer of {capacity} transitions takes at least {:.2} GiB ({} bytes per transition \
                 before its frames), above this server's replay budget of {:.2} GiB (limits.replay_memory_bytes)",
                gib(least),
                radserve_replay::MIN_BYTES_PER_TRANSITION,
                gib(budget)
            )));
        }
        Ok(())
    }

    /// Reserve memory for `what` against the server's budget (a stream's batches, an acting
    /// channel); held until the reservation is dropped.
    pub fn reserve_memory(&self, caller: &Principal, bytes: u64, what: &str) -> Result<Reservation, CoreError> {
        self.budget.try_reserve_within(self.quota(caller).as_ref(), bytes, what)
    }

    /// Reserve the batches a sample stream holds at once, `bytes` for (`prefetch` + 2) batches: within
    /// the per-stream limit and the memory budget, for as long as the reservation lives.
    pub fn reserve_stream(&self, caller: &Principal, bytes: u64, prefetch: usize) -> Result<Reservation, CoreError> {
        let limit = self.limits.stream_memory_bytes;
        if bytes > limit {
            return Err(CoreError::TooLarge(format!(
                "this stream would hold {bytes} bytes ((prefetch {prefetch} + 2) batches of observations, and a prioritized \
                 stream's priorities and sum tree), over this server's limit of {limit} (limits.stream_memory_bytes): \
                 lower prefetch or batch_size"
            )));
        }
        self.budget.try_reserve_within(
            self.quota(caller).as_ref(),
            bytes,
            &format!("a sample stream of (prefetch {prefetch} + 2) batches"),
        )
    }

    /// The server's memory budget: (bytes reserved now, limit).
    pub fn memory(&self) -> (u64, u64) {
        (self.budget.used(), self.budget.limit())
    }

    pub(super) fn release(&self, owner: &Arc<str>, num_envs: usize, sessions: usize) {
        let mut registry = self.sessions.lock().expect("registry lock");
        registry.reserved_envs -= num_envs;
        registry.reserved_sessions -= sessions;
        if let Some(usage) = registry.principals.get_mut(owner) {
            usage.envs -= num_envs;
            usage.sessions -= sessions;
        }
    }
}

/// The most bytes of observations one step may return for all of a session's envs. A step's
/// response carries them and, when every episode ends at once, as many final observations; both
/// must fit in one gRPC message (the service's 256 MiB).
pub const MAX_STEP_OBSERVATION_BYTES: usize = 96 << 20;

/// The buffers a session allocates for its frames: the stacks, the frame and final frame per env in
/// the memory shared with workers, and a step's observations and final observations as returned.
fn frame_buffer_bytes(session: &Session) -> u64 {
    let frame = session.frame_spec.observation.num_bytes() as u64;
    let observation = session.observation_space.num_bytes() as u64;
    let per_env = frame * session.config.frame_stack as u64 + 2 * frame + 2 * observation;
    per_env.saturating_mul(session.num_envs() as u64)
}

/// Refuses a session whose step observations could not be sent in one response.
fn check_observation_bytes(session: &Session) -> Result<(), CoreError> {
    let per_env = session.observation_space.num_bytes();
    let total = per_env.saturating_mul(session.num_envs());
    if total > MAX_STEP_OBSERVATION_BYTES {
        return Err(CoreError::TooLarge(format!(
            "{} envs of {} observe {per_env} bytes each ({} as viewed), {total} bytes a step; the most a step \
             may return is {MAX_STEP_OBSERVATION_BYTES} bytes: use fewer envs, smaller frames or a smaller frame_stack",
            session.num_envs(),
            session.config.env.full(),
            session.observation_space.describe(),
        )));
    }
    Ok(())
}

pub(super) fn gib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 30) as f64
}

/// Refuses a `batch_size` above `num_envs`, and a buffer for a session in EnvPool's asynchronous mode,
/// before anything is built.
fn check_batch_size(options: &Options, num_envs: usize, extras: &SessionExtras) -> Result<(), CoreError> {
    let batch = options.get(catalog::BATCH_SIZE).and_then(OptionValue::as_int).unwrap_or(0);
    if batch as usize > num_envs {
        return Err(CoreError::InvalidOption(format!(
            "option 'batch_size' is {batch}, above num_envs {num_envs}: a recv returns at most every env; give \
             batch_size in [1, {num_envs}] (below num_envs for EnvPool's asynchronous mode) or 0"
        )));
    }
    if let Some(batch) = catalog::native_async_batch(options, num_envs) {
        // The native engine steps a whole group at a time: recv returns the first group done.
        if !num_envs.is_multiple_of(batch) || num_envs / batch > catalog::MAX_ASYNC_GROUPS {
            return Err(CoreError::InvalidOption(format!(
                "option 'batch_size' is {batch} with num_envs {num_envs}: the native engine steps a session's envs in \
                 groups of batch_size (each recv returns the first group done), so num_envs must be a multiple of \
                 batch_size, in at most {} groups; give such a batch_size, or engine='envpool' for any batch_size",
                catalog::MAX_ASYNC_GROUPS
            )));
        }
    }
    if let (Some(batch), Some(_)) = (catalog::async_batch(options, num_envs), extras.buffer) {
        // Transitions would be recorded per recv, in the order envs come back: not built.
        return Err(CoreError::InvalidSession(format!(
            "a session with batch_size {batch} below num_envs {num_envs} (EnvPool's asynchronous mode) keeps no replay \
             or rollout buffer: create it without one, or with batch_size 0"
        )));
    }
    Ok(())
}

/// A session's place among the server's and its principal's sessions and envs, counted by
/// `SessionManager::reserve`: given back when dropped, unless `keep` hands it to the registry.
pub(super) struct Place<'a> {
    manager: &'a SessionManager,
    owner: Arc<str>,
    num_envs: usize,
    kept: bool,
}

impl Place<'_> {
    /// The registry holds the place from now on (`close_entry` gives it back); its owner.
    fn keep(mut self) -> Arc<str> {
        self.kept = true;
        self.owner.clone()
    }
}

impl Drop for Place<'_> {
    fn drop(&mut self) {
        if !self.kept {
            self.manager.release(&self.owner, self.num_envs, 1);
        }
    }
}

/// A session name taken by a session being created: given back when dropped, unless `keep` hands it
/// to the registered session (whose close gives it back).
pub(super) struct NameHold<'a> {
    manager: &'a SessionManager,
    owner: Arc<str>,
    name: String,
    kept: bool,
}

impl NameHold<'_> {
    fn keep(mut self) {
        self.kept = true;
    }
}

impl Drop for NameHold<'_> {
    fn drop(&mut self) {
        if !self.kept {
            let key = (self.owner.clone(), std::mem::take(&mut self.name));
            self.manager.sessions.lock().expect("registry lock").names.remove(&key);
        }
    }
}

/// Bytes counted against the replay budget (`limits.replay_memory_bytes`) for a buffer being made:
/// given back when dropped, unless `keep` hands them to the registered session (whose close gives
/// them back through `release_replay`).
pub(super) struct ReplayShare<'a> {
    pub(super) manager: &'a SessionManager,
    pub(super) bytes: u64,
    pub(super) kept: bool,
}

impl ReplayShare<'_> {
    fn keep(mut self) {
        self.kept = true;
    }
}

impl Drop for ReplayShare<'_> {
    fn drop(&mut self) {
        if !self.kept {
            self.manager.sessions.lock().expect("registry lock").reserved_replay_bytes -= self.bytes;
        }
    }
}
