//! Every failure a handler answers with, and the one place each becomes a gRPC status.

use radserve_core::CoreError;
use radserve_replay::ReplayError;
use thiserror::Error;
use tonic::{Code, Status};

#[derive(Debug, Error)]
pub enum ServiceError {
    #[error(transparent)]
    Core(#[from] CoreError),
    #[error(transparent)]
    Replay(#[from] ReplayError),
    /// A message that does not say what the RPC needs: a missing field, an unknown enum value, a
    /// negative dimension, a size outside its range, a message out of the stream's order.
    #[error("{0}")]
    BadRequest(String),
    /// The session already has what the request would open (one shared-stepping channel per session).
    #[error("{0}")]
    AlreadyOpen(String),
    /// The request does not fit the state it finds (a dm_env_rpc step before joining a world).
    #[error("{0}")]
    FailedPrecondition(String),
    /// The client's deadline passed before the call could start, or a stream's first message did
    /// not come in time.
    #[error("{0}")]
    TooLate(String),
    /// The server began to shut down: the stream ends (its session is closed at exit).
    #[error("the server is shutting down; this stream ended (its session is closed at exit)")]
    StreamEnded,
    /// The request carries no credentials the server accepts (no token, an unknown token).
    #[error("{0}")]
    Unauthenticated(String),
    /// The caller is known but may not do this (an admin-only call, a method its token lacks).
    #[error("{0}")]
    PermissionDenied(String),
    /// A part of a protocol radserve does not serve (a dm_env_rpc extension).
    #[error("{0}")]
    Unimplemented(String),
    /// The server failed in a way that is not the request's fault.
    #[error("{0}")]
    Internal(String),
    /// What the transport answered for a message it could not take (undecodable bytes, a stream
    /// the client reset), passed on with its code.
    #[error("{}", .0.message())]
    Transport(Status),
}

pub type Result<T> = std::result::Result<T, ServiceError>;

impl From<ServiceError> for Status {
    /// Every error gets its code on purpose: there is no catch-all arm, so a new variant (here or
    /// in the core's and replay's enums) must be placed (qdrant's StorageError -> Status is the model).
    fn from(error: ServiceError) -> Status {
        let code = match &error {
            ServiceError::Core(core) => match core {
                CoreError::UnknownEnv { .. } | CoreError::UnknownSession(_) => Code::NotFound,
                CoreError::InvalidOption(_)
                | CoreError::OutOfBounds(_)
                | CoreError::InvalidActions(_)
                | CoreError::InvalidMask(_)
                | CoreError::InvalidSeed { .. }
                | CoreError::InvalidView { .. }
                | CoreError::InvalidSession(_)
                | CoreError::CreateFailed { .. } => Code::InvalidArgument,
                CoreError::Replay(replay) => replay_code(replay),
                CoreError::NotReset | CoreError::NoReplayBuffer(_) => Code::FailedPrecondition,
                CoreError::OverLimit(_) | CoreError::OutOfMemory(_) => Code::ResourceExhausted,
                CoreError::TooLarge(_) => Code::InvalidArgument,
                CoreError::WorkersUnavailable(_) | CoreError::ShuttingDown => Code::Unavailable,
                CoreError::NameTaken(_) => Code::AlreadyExists,
                CoreError::BadSnapshot(_) | CoreError::Acting(_) => Code::FailedPrecondition,
                CoreError::Policy(policy) => policy_code(policy),
                CoreError::Simulator(_) | CoreError::Host(_) => Code::Internal,
            },
            ServiceError::Replay(replay) => replay_code(replay),
            ServiceError::BadRequest(_) => Code::InvalidArgument,
            ServiceError::AlreadyOpen(_) | ServiceError::FailedPrecondition(_) => Code::FailedPrecondition,
            ServiceError::TooLate(_) => Code::DeadlineExceeded,
            ServiceError::StreamEnded => Code::Unavailable,
            ServiceError::Unauthenticated(_) => Code::Unauthenticated,
            ServiceError::PermissionDenied(_) => Code::PermissionDenied,
            ServiceError::Unimplemented(_) => Code::Unimplemented,
            ServiceError::Internal(_) => Code::Internal,
            ServiceError::Transport(status) => status.code(),
        };
        Status::new(code, error.to_string())
    }
}

/// A refused model is the request's fault; one past the policy runtime's memory or time is over a
/// limit; a server without ONNX Runtime cannot act at all.
fn policy_code(error: &radserve_policy::PolicyError) -> Code {
    use radserve_policy::PolicyError;
    match error {
        PolicyError::NotOnnx(_) | PolicyError::Unsupported(_) | PolicyError::Mismatch(_) | PolicyError::Runtime(_) | PolicyError::NonFinite(_) => {
            Code::InvalidArgument
        }
        PolicyError::Unavailable(_) => Code::Unimplemented,
        PolicyError::Exhausted(_) => Code::ResourceExhausted,
    }
}

fn replay_code(error: &ReplayError) -> Code {
    match error {
        ReplayError::InvalidArgument(_) | ReplayError::Augment(_) => Code::InvalidArgument,
        ReplayError::FailedPrecondition(_) => Code::FailedPrecondition,
        ReplayError::Cancelled => Code::Cancelled,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(error: impl Into<ServiceError>) -> Status {
        Status::from(error.into())
    }

    #[test]
    fn codes_follow_the_kind_of_mistake() {
        let unknown = status(CoreError::UnknownEnv { id: "dmc/x".into(), suggestions: vec!["dmc/y".into()] });
        assert_eq!(unknown.code(), Code::NotFound);
        assert!(unknown.message().contains("did you mean dmc/y"));
        assert_eq!(status(CoreError::InvalidActions("bad".into())).code(), Code::InvalidArgument);
        assert_eq!(status(CoreError::OverLimit("full".into())).code(), Code::ResourceExhausted);
        assert_eq!(status(CoreError::NotReset).code(), Code::FailedPrecondition);
        let capacity = radserve_replay::check_capacity(usize::MAX).unwrap_err();
        assert_eq!(status(CoreError::Replay(capacity)).code(), Code::InvalidArgument);
        assert_eq!(status(CoreError::ShuttingDown).code(), Code::Unavailable);
        assert_eq!(status(CoreError::Acting("acting".into())).code(), Code::FailedPrecondition);
        let policy = CoreError::Policy(radserve_policy::PolicyError::Unsupported("operator Loop".into()));
        assert_eq!(status(policy).code(), Code::InvalidArgument);
        let augment = radserve_augment::Pipeline::parse("crpo").unwrap_err();
        let status = status(ReplayError::Augment(augment));
        assert_eq!(status.code(), Code::InvalidArgument);
        assert!(status.message().contains("did you mean \"crop\""), "{}", status.message());
        let ended = Status::from(ServiceError::StreamEnded);
        assert_eq!((ended.code(), ended.message()), (Code::Unavailable, ServiceError::StreamEnded.to_string().as_str()));
    }
}
