use thiserror::Error;

/// Everything that can go wrong in the simulator core. The service maps each variant to a gRPC code
/// on purpose (no catch-all arm), so a new variant has to be placed there.
#[derive(Debug, Error)]
pub enum SimError {
    #[error("unknown environment id '{}'{}", crate::bounds::clip(.id), suggestion_text(.suggestions))]
    UnknownEnv { id: String, suggestions: Vec<String> },

    #[error("{0}")]
    InvalidOption(String),

    /// A request that does not fit the session: action shape, dtype, bounds, NaN, seed range.
    #[error("{0}")]
    InvalidArgument(String),

    #[error("unknown session '{}' (it was never created, or it was closed)", crate::bounds::clip(.0))]
    UnknownSession(String),

    /// The request is valid but the session is not in a state to take it.
    #[error("{0}")]
    FailedPrecondition(String),

    /// A server limit (sessions, environments) would be exceeded.
    #[error("{0}")]
    LimitExceeded(String),

    /// The simulator refused to build the environment with these options.
    #[error("the simulator could not create {env_id}: {message}")]
    CreateFailed { env_id: String, message: String },

    /// The simulator failed in a way that is not the caller's fault.
    #[error("simulator failure: {0}")]
    Simulator(String),

    /// No worker process could be started or reached.
    #[error("simulator workers unavailable: {0}")]
    WorkersUnavailable(String),

    #[error("the server is shutting down")]
    ShuttingDown,
}

fn suggestion_text(suggestions: &[String]) -> String {
    if suggestions.is_empty() {
        "; list the available ids with ListEnvs (`radserve envs`)".to_string()
    } else {
        format!("; did you mean {}?", suggestions.join(", "))
    }
}
