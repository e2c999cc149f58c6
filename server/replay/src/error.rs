use radserve_augment::AugmentError;
use thiserror::Error;

#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum ReplayError {
    /// A request that can never be served as asked (batch size zero or above capacity...).
    #[error("{0}")]
    InvalidArgument(String),
    /// The session has no buffer of the kind asked for.
    #[error("{0}")]
    FailedPrecondition(String),
    #[error(transparent)]
    Augment(#[from] AugmentError),
    /// The stream's client left while its batch was being made (never sent to anyone).
    #[error("the stream was cancelled")]
    Cancelled,
}

pub type Result<T> = std::result::Result<T, ReplayError>;
