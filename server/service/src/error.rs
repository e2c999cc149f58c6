use radserve_replay::ReplayError;
use radserve_core::CoreError;
use tonic::{Code, Status};

/// Every core error gets its code on purpose: there is no catch-all arm, so a new variant must be
/// placed here (qdrant's StorageError -> Status conversion is the model).
pub fn to_status(error: CoreError) -> Status {
    let code = match &error {
        CoreError::UnknownEnv { .. } | CoreError::UnknownSession(_) => Code::NotFound,
        CoreError::InvalidOption(_) | CoreError::InvalidArgument(_) | CoreError::CreateFailed { .. } => {
            Code::InvalidArgument
        }
        CoreError::FailedPrecondition(_) => Code::FailedPrecondition,
        CoreError::LimitExceeded(_) => Code::ResourceExhausted,
        CoreError::WorkersUnavailable(_) | CoreError::ShuttingDown => Code::Unavailable,
        CoreError::Simulator(_) => Code::Internal,
    };
    Status::new(code, error.to_string())
}

/// The replay crate's errors, placed the same way.
pub fn replay_status(error: ReplayError) -> Status {
    let code = match &error {
        ReplayError::InvalidArgument(_) | ReplayError::Augment(_) => Code::InvalidArgument,
        ReplayError::FailedPrecondition(_) => Code::FailedPrecondition,
        ReplayError::OverBudget(_) => Code::ResourceExhausted,
        ReplayError::Cancelled => Code::Cancelled,
    };
    Status::new(code, error.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_follow_the_kind_of_mistake() {
        let unknown = CoreError::UnknownEnv { id: "dmc/x".into(), suggestions: vec!["dmc/y".into()] };
        let status = to_status(unknown);
        assert_eq!(status.code(), Code::NotFound);
        assert!(status.message().contains("did you mean dmc/y"));
        assert_eq!(to_status(CoreError::InvalidArgument("bad".into())).code(), Code::InvalidArgument);
        assert_eq!(to_status(CoreError::LimitExceeded("full".into())).code(), Code::ResourceExhausted);
        assert_eq!(to_status(CoreError::ShuttingDown).code(), Code::Unavailable);
        let augment = radserve_augment::Pipeline::parse("crpo").unwrap_err();
        let status = replay_status(ReplayError::Augment(augment));
        assert_eq!(status.code(), Code::InvalidArgument);
        assert!(status.message().contains("did you mean \"crop\""), "{}", status.message());
    }
}
