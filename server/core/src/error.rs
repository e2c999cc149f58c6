use thiserror::Error;

use radserve_replay::ReplayError;

use crate::simulators::SimulatorError;

/// Everything that can go wrong in the core, by what went wrong. The service maps each variant to a
/// gRPC code on purpose (no catch-all arm), so a new variant has to be placed there.
#[derive(Debug, Error)]
pub enum CoreError {
    #[error("unknown environment id '{}'{}", crate::bounds::clip(.id), suggestion_text(.suggestions))]
    UnknownEnv { id: String, suggestions: Vec<String> },

    /// An option the env's family does not have, or a value of the wrong type or range.
    #[error("{0}")]
    InvalidOption(String),

    /// A request field longer or larger than the server accepts, refused before any work.
    #[error("{0}")]
    OutOfBounds(String),

    /// Actions that do not fit the action space: dtype, shape, size, NaN, bounds.
    #[error("{0}")]
    InvalidActions(String),
    /// A reset mask, skip mask or per-env seed list that does not fit the session.
    #[error("{0}")]
    InvalidMask(String),

    /// A seed beyond the simulators' 32-bit seeds.
    #[error("seed + num_envs must be at most {max} (simulators take 32-bit seeds); got seed {seed} with {num_envs} envs")]
    InvalidSeed { seed: u64, num_envs: usize, max: u64 },

    /// An evaluation view that is not a view, or does not fit the observation.
    #[error("observation_view {text:?}: {message}")]
    InvalidView { text: String, message: String },

    /// A session that cannot be built as asked: no envs, a buffer its observations cannot go in.
    #[error("{0}")]
    InvalidSession(String),

    /// A replay or rollout buffer that cannot be laid out as asked.
    #[error(transparent)]
    Replay(#[from] ReplayError),

    #[error("unknown session '{}' (it was never created, or it was closed)", crate::bounds::clip(.0))]
    UnknownSession(String),

    /// Step before the first Reset, or after a step that failed.
    #[error("call Reset on this session before Step (AsyncReset before Send/Recv for a session in EnvPool's asynchronous mode)")]
    NotReset,

    /// A sample stream on a session without a buffer.
    #[error("session {0} keeps no replay buffer; create it with a replay capacity")]
    NoReplayBuffer(String),

    /// A configured limit of the server that what is open now reaches: sessions, envs, streams,
    /// replay bytes reserved (worth retrying once something closes).
    #[error("{0}")]
    OverLimit(String),

    /// A request larger than a fixed limit of the server allows whatever else is open: envs per
    /// session, a step's observations, a buffer or a stream above its whole budget. No retry can
    /// succeed.
    #[error("{0}")]
    TooLarge(String),

    /// The server's memory budget, or the host's memory or file descriptors.
    #[error("{0}")]
    OutOfMemory(String),

    /// The simulator refused to build the environment with these options.
    #[error("the simulator could not create {env_id}: {message}")]
    CreateFailed { env_id: String, message: String },

    /// The simulator failed in a way that is not the caller's fault.
    #[error("simulator failure: {0}")]
    Simulator(String),

    /// The server's host failed it in a way that is neither the caller's fault nor a simulator's (a
    /// shared-memory file it could not make, for a reason other than exhaustion).
    #[error("server failure: {0}")]
    Host(String),

    /// No worker process could be started or reached.
    #[error("simulator workers unavailable: {0}")]
    WorkersUnavailable(String),

    #[error("the server is shutting down")]
    ShuttingDown,

    /// A session name its owner already uses for a live session.
    #[error("{0}")]
    NameTaken(String),

    /// A named session's snapshot that cannot be restored, on a server configured to refuse it.
    #[error("{0}")]
    BadSnapshot(String),

    /// A call that steps or resets a session whose envs the server's actor is stepping
    /// (StartActing), or an acting call that does not fit the session's state.
    #[error("{0}")]
    Acting(String),

    /// A policy (SetPolicy) the server refuses: not ONNX, an unsupported operator, a model that does
    /// not fit the session or its head.
    #[error(transparent)]
    Policy(#[from] radserve_policy::PolicyError),
}

impl From<SimulatorError> for CoreError {
    /// A simulator's failure as the caller sees it. A refusal to build envs is placed by the caller,
    /// which knows the env id (`CoreError::CreateFailed`); anywhere else it is the simulator's fault.
    fn from(error: SimulatorError) -> CoreError {
        match error {
            SimulatorError::Refused(message) | SimulatorError::Failed(message) | SimulatorError::Lost(message) => {
                CoreError::Simulator(message)
            }
            SimulatorError::Unavailable(message) => CoreError::WorkersUnavailable(message),
            SimulatorError::OutOfResources(message) => CoreError::OutOfMemory(message),
        }
    }
}

impl CoreError {
    /// A request over a configured limit: `TooLarge` when the request alone exceeds it (no retry can
    /// fit it), `OverLimit` when it exceeds what is left of it now (it fits once something closes).
    pub(crate) fn over_limit(alone_exceeds: bool, message: String) -> CoreError {
        if alone_exceeds {
            CoreError::TooLarge(message)
        } else {
            CoreError::OverLimit(message)
        }
    }
}

/// An allocation that failed: out of file descriptors or memory is a limit of this server
/// (RESOURCE_EXHAUSTED, worth retrying elsewhere or later), anything else a failure of the host.
pub fn resource_error(what: &str, error: &std::io::Error) -> CoreError {
    match exhaustion(what, error) {
        Some(message) => CoreError::OutOfMemory(message),
        None => CoreError::Host(format!("{what}: {error}")),
    }
}

impl SimulatorError {
    /// An allocation for a group that failed, placed as [`resource_error`] places it.
    pub fn allocation(what: &str, error: &std::io::Error) -> SimulatorError {
        match exhaustion(what, error) {
            Some(message) => SimulatorError::OutOfResources(message),
            None => SimulatorError::Failed(format!("{what}: {error}")),
        }
    }
}

/// What to say when `error` means the host ran out of file descriptors or memory.
fn exhaustion(what: &str, error: &std::io::Error) -> Option<String> {
    match error.raw_os_error() {
        Some(libc::EMFILE | libc::ENFILE) => {
            Some(format!("{what}: the server is out of file descriptors ({error}); try again later"))
        }
        Some(libc::ENOMEM | libc::ENOSPC) => Some(format!("{what}: the server is out of memory ({error})")),
        _ => None,
    }
}

fn suggestion_text(suggestions: &[String]) -> String {
    if suggestions.is_empty() {
        "; list the available ids with ListEnvs (`radserve envs`)".to_string()
    } else {
        format!("; did you mean {}?", suggestions.join(", "))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failed_allocation_is_exhaustion_or_the_hosts_failure_never_a_simulators() {
        let full = resource_error("creating the ring", &std::io::Error::from_raw_os_error(libc::EMFILE));
        assert!(matches!(&full, CoreError::OutOfMemory(message) if message.contains("out of file descriptors")), "{full}");
        let denied = resource_error("creating the ring", &std::io::Error::from_raw_os_error(libc::EACCES));
        assert!(matches!(&denied, CoreError::Host(_)), "{denied:?}");
        assert!(denied.to_string().starts_with("server failure: creating the ring"), "{denied}");
    }
}
