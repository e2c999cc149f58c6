//! What the manager's callers give and get: limits, a session's extras, what a client learns.

use std::sync::{Arc, RwLock};
use std::time::Duration;

use radserve_replay::{ObservationFormat, ProducerPermit, ReplayBuffer};
use serde::{Deserialize, Serialize};
use tokio::sync::Mutex;

use crate::catalog::{EnvId, Options};
use crate::session::{AutoresetMode, Session};
use crate::space::Space;

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    /// Sessions open at once on the server (every principal's together).
    pub max_sessions: usize,
    /// Environments in one session (`num_envs`).
    pub max_envs_per_session: usize,
    /// Environments across all sessions of the server.
    pub max_total_envs: usize,
    /// Bytes all sessions' replay buffers may take together (computed up front at creation).
    pub replay_memory_bytes: u64,
    /// SampleBatches streams open at once on one session (each has a sampler thread).
    pub max_streams_per_session: usize,
    /// Bytes of batches one sample stream may hold at once: (prefetch + 2) batches of observations.
    pub stream_memory_bytes: u64,
    /// Seconds a session may go without a call on it and without an open stream before the server
    /// closes it (a learner that crashed leaves its sessions behind); 0 keeps sessions until closed.
    pub session_idle_timeout_s: u64,
    /// Seconds an open stream may go unused and still keep its session from counting as idle: a
    /// sample stream whose client took no batch (an unread stream: its batches wait in flow
    /// control), a shared-stepping channel or dm_env_rpc join whose client sent no request. Past it the
    /// session is idle since its last call or batch, and session_idle_timeout_s applies. 0: an open
    /// stream keeps its session however long it is unused.
    pub unread_stream_timeout_s: u64,
    /// Bytes every session, buffer and stream of the server may take together, reserved before each
    /// is allocated (envs at their measured cost per family, frames, replay, stream batches). 0: three
    /// quarters of the host's (or the container's) memory, less 512 MiB per worker.
    pub memory_bytes: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_sessions: 64,
            max_envs_per_session: 256,
            max_total_envs: 1024,
            replay_memory_bytes: 8 << 30,
            max_streams_per_session: 4,
            stream_memory_bytes: 4 << 30,
            session_idle_timeout_s: 300,
            unread_stream_timeout_s: 600,
            memory_bytes: 0,
        }
    }
}

/// What a session may have besides its environments.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct SessionExtras {
    /// A replay or rollout buffer recording every step.
    pub buffer: Option<BufferRequest>,
    /// Return observations through this evaluation view (`center_crop(84)`, `center_translate(108)`).
    pub observation_view: Option<String>,
    /// A name unique among its owner's live sessions; with `[replay] snapshot_dir` set, its replay
    /// is snapshotted and restored when a session of the same name is created after a restart.
    pub name: Option<String>,
}

/// The buffer a session is created with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BufferRequest {
    /// Uniform replay over the last `capacity` transitions.
    Replay { capacity: usize },
    /// The last `steps` steps of every env, for on-policy learners.
    Rollout { steps: usize },
}

/// A session's replay buffer, as a client sees it.
#[derive(Clone, Debug, PartialEq)]
pub struct ReplayInfo {
    pub capacity: usize,
    /// Transitions that can be sampled now.
    pub size: usize,
    pub inserts: u64,
    pub samples: u64,
    /// Minibatches sampled since creation.
    pub batches: u64,
    /// Minibatches sampled per second, over the last 5 seconds.
    pub batches_per_second: f64,
    pub memory_bytes: u64,
    pub frames_per_transition: f64,
    /// SampleBatches streams producing from it now.
    pub active_streams: usize,
    /// For a rollout buffer: the steps per env it keeps.
    pub rollout_steps: Option<usize>,
    /// For a named session's replay on a server that snapshots.
    pub snapshot: Option<SnapshotInfo>,
}

/// A named session's replay snapshot.
#[derive(Clone, Debug, PartialEq)]
pub struct SnapshotInfo {
    /// Transitions restored from the snapshot when the session was created (0: none).
    pub restored_transitions: u64,
    /// Bytes the snapshot takes on disk.
    pub disk_bytes: u64,
    /// How old the snapshot on disk is (None: none written yet).
    pub age: Option<Duration>,
    /// Frames recorded since the snapshot on disk (0: it holds everything recorded so far).
    pub pending_frames: u64,
}

/// What a sampler needs of a session: its buffer, what its observations and actions are, and the
/// stream's place among the session's streams (reserved; dropping it frees the place).
pub struct ReplaySource {
    pub buffer: Arc<RwLock<ReplayBuffer>>,
    pub format: ObservationFormat,
    pub action_space: Space,
    pub permit: ProducerPermit,
}

/// A catalog entry: an id with its default options and the spaces they give.
#[derive(Clone, Debug)]
pub struct CatalogEntry {
    pub id: EnvId,
    pub default_options: Options,
    /// (stacked observation space, action space), or why the simulator could not build the env.
    pub spaces: Result<(Space, Space), String>,
}

/// What a client learns about a session.
#[derive(Clone, Debug)]
pub struct SessionInfo {
    pub session_id: String,
    pub name: Option<String>,
    pub env_id: String,
    pub num_envs: usize,
    pub seed: u64,
    pub options: Options,
    pub observation_space: Space,
    pub action_space: Space,
    pub frame_stack: usize,
    pub autoreset_mode: AutoresetMode,
    pub total_env_steps: u64,
    pub episodes_completed: u64,
    pub replay: Option<ReplayInfo>,
    /// Its server-side actor, once a policy was set.
    pub acting: Option<super::ActingStatus>,
}

pub type SharedSession = Arc<Mutex<Session>>;

/// One open session as an operator sees it (ListSessions).
#[derive(Clone, Debug, PartialEq)]
pub struct SessionSummary {
    pub session_id: String,
    pub name: Option<String>,
    /// The principal that created it.
    pub owner: String,
    pub env_id: String,
    pub num_envs: usize,
    pub memory_bytes: u64,
    pub idle: Duration,
    pub open_streams: usize,
    pub age: Duration,
    /// Transitions its replay buffer holds now, and the bytes the buffer takes (0 without one).
    pub replay_transitions: u64,
    pub replay_bytes: u64,
    /// A named session's replay snapshot.
    pub snapshot: Option<SnapshotInfo>,
}
