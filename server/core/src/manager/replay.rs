//! A session's replay (or rollout) buffer: made within the replay budget, and handed to samplers.

use std::sync::{Arc, RwLock};

use radserve_replay::{BufferKind, ObservationFormat, PriorityUpdate, ReplayBuffer, ReplayLayout};

use super::admission::{gib, ReplayShare};
use super::{BufferRequest, ReplayInfo, ReplaySource, SessionManager};
use crate::budget::{MemoryBudget, Reservation};
use crate::error::CoreError;
use crate::principal::Principal;
use crate::session::Session;
use crate::space::DType;

impl SessionManager {
    /// Give `session` a replay (or rollout) buffer if the server's budget allows it.
    pub(super) fn attach_replay(
        &self,
        session: &mut Session,
        buffer: BufferRequest,
        quota: Option<&Arc<MemoryBudget>>,
    ) -> Result<(Reservation, ReplayShare<'_>), CoreError> {
        let frame = &session.frame_spec.observation;
        if !matches!(frame.dtype(), DType::Uint8 | DType::Float32) {
            return Err(CoreError::InvalidSession(format!(
                "replay keeps uint8 images or float32 vectors; {} observes {}",
                session.config.env.full(),
                frame.describe()
            )));
        }
        let (num_envs, frame_stack) = (session.num_envs(), session.config.frame_stack);
        let (frame_bytes, action_bytes) = (frame.num_bytes(), session.frame_spec.action.num_bytes());
        let layout = match buffer {
            BufferRequest::Replay { capacity } => {
                ReplayLayout { kind: BufferKind::Replay, capacity, num_envs, frame_stack, frame_bytes, action_bytes }
            }
            BufferRequest::Rollout { steps } => ReplayLayout::rollout(steps, num_envs, frame_stack, frame_bytes, action_bytes),
        };
        let capacity = layout.capacity;
        layout.validate()?;
        let bytes = layout.memory_bytes() as u64;
        let share = {
            let mut registry = self.sessions.lock().expect("registry lock");
            let budget = self.limits.replay_memory_bytes;
            if registry.reserved_replay_bytes.saturating_add(bytes) > budget {
                return Err(CoreError::over_limit(bytes > budget, format!(
                    "a replay buffer of {capacity} transitions for {} envs of {} takes {:.2} GiB ({} bytes per frame, \
                     {:.3} frames per transition); with the {:.2} GiB already reserved it would exceed this server's \
                     replay budget of {:.2} GiB (limits.replay_memory_bytes)",
                    layout.num_envs,
                    session.config.env.full(),
                    gib(bytes),
                    layout.frame_bytes,
                    layout.frames_per_transition(),
                    gib(registry.reserved_replay_bytes),
                    gib(budget)
                )));
            }
            registry.reserved_replay_bytes += bytes;
            ReplayShare { manager: self, bytes, kept: false }
        };
        let reservation = self.budget.try_reserve_within(quota, bytes, &format!("a replay buffer of {capacity} transitions"))?;
        session.attach_replay(Arc::new(RwLock::new(ReplayBuffer::new(layout)?)));
        Ok((reservation, share))
    }

    pub(super) fn release_replay(&self, session: &Session) {
        if let Some(replay) = session.replay() {
            let bytes = replay.read().expect("replay lock").layout().memory_bytes() as u64;
            self.sessions.lock().expect("registry lock").reserved_replay_bytes -= bytes;
        }
    }

    /// Replace the priorities of a session's sampled transitions (see
    /// [`ReplayBuffer::update_priorities`]).
    pub async fn update_priorities(
        &self,
        caller: &Principal,
        session_id: &str,
        keys: &[u64],
        priorities: &[f64],
    ) -> Result<PriorityUpdate, CoreError> {
        let buffer = {
            let session = self.get(caller, session_id)?;
            let session = session.lock().await;
            session.replay().cloned().ok_or_else(|| CoreError::NoReplayBuffer(session_id.to_string()))?
        };
        let update = buffer.write().expect("replay lock").update_priorities(keys, priorities)?;
        Ok(update)
    }

    /// The replay buffer of a session, with what a sampler needs to know about it.
    pub async fn replay_source(&self, caller: &Principal, session_id: &str) -> Result<ReplaySource, CoreError> {
        let session = self.get(caller, session_id)?;
        let session = session.lock().await;
        let Some(buffer) = session.replay() else {
            return Err(CoreError::NoReplayBuffer(session_id.to_string()));
        };
        // Reserved here, atomically: concurrent requests cannot all pass a check made before any
        // of them is counted.
        let max = self.limits.max_streams_per_session;
        let Some(permit) = buffer.read().expect("replay lock").admit_producer(max) else {
            return Err(CoreError::OverLimit(format!(
                "session {session_id} already has {max} sample streams open, this server's limit \
                 (limits.max_streams_per_session); close one first"
            )));
        };
        let frame = &session.frame_spec.observation;
        let format = match (frame.dtype(), frame.shape()) {
            (DType::Uint8, &[channels, height, width]) => {
                ObservationFormat::Image(radserve_augment::FrameShape::new(session.config.frame_stack, channels, height, width))
            }
            _ => ObservationFormat::State(session.config.frame_stack * frame.num_elements()),
        };
        Ok(ReplaySource { buffer: buffer.clone(), format, action_space: session.frame_spec.action.clone(), permit })
    }
}

pub(super) fn replay_info(replay: &ReplayBuffer) -> ReplayInfo {
    let layout = replay.layout();
    ReplayInfo {
        capacity: layout.capacity,
        size: replay.len(),
        inserts: replay.counters().inserts,
        samples: replay.counters().samples,
        batches: replay.counters().batches,
        batches_per_second: replay.batches_per_second(),
        memory_bytes: layout.memory_bytes() as u64,
        frames_per_transition: layout.frames_per_transition(),
        active_streams: replay.active_producers(),
        rollout_steps: match layout.kind {
            BufferKind::Rollout { steps } => Some(steps),
            BufferKind::Replay => None,
        },
        snapshot: None,
    }
}
