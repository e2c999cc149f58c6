use thiserror::Error;

/// Everything that can be wrong with a pipeline or a batch, found before any batch is touched.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum AugmentError {
    /// The text form does not parse.
    #[error("augmentation pipeline {text:?}, at character {at}: {message}")]
    Syntax { text: String, at: usize, message: String },
    /// A name that is not an augmentation.
    #[error("unknown augmentation {name:?}{suggestion}; expected one of: {expected}")]
    UnknownAugmentation { name: String, suggestion: String, expected: String },
    /// A parameter outside its range, or one the augmentation does not take.
    #[error("{augmentation}: {message}")]
    InvalidParameter { augmentation: &'static str, message: String },
    /// The augmentation cannot apply to this observation (a crop larger than the frame, rotate on a
    /// non-square frame, an image augmentation on state vectors...).
    #[error("{augmentation} does not fit the observation {observation}: {message}")]
    DoesNotFit { augmentation: &'static str, observation: String, message: String },
    /// A pipeline longer than the server accepts (text length, number of stages).
    #[error("{message}")]
    TooLong { message: String },
    /// The caller's buffers do not match the plan's shapes.
    #[error("buffer does not match the plan: {message}")]
    Buffer { message: String },
}

pub type Result<T> = std::result::Result<T, AugmentError>;
