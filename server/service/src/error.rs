use radserve_replay::ReplayError;
use radserve_sim::SimError;
use tonic::{Code, Status};

/// Every core error gets its code on purpose: there is no catch-all arm, so a new variant must be
/// placed here (qdrant's StorageError -> Status conversion is the model).
pub fn to_status(error: SimError) -> Status {
    let code = match &error {
        SimError::UnknownEnv { .. } | SimError::UnknownSession(_) => Code::NotFound,
        SimError::InvalidOption(_) | SimError::InvalidArgument(_) | SimError::CreateFailed { .. } => {
            Code::InvalidArgument
        }
        SimError::FailedPrecondition(_) => Code::FailedPrecondition,
        SimError::LimitExceeded(_) => Code::ResourceExhausted,
        SimError::WorkersUnavailable(_) | SimError::ShuttingDown => Code::Unavailable,
        SimError::Simulator(_) => Code::Internal,
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
        let unknown = SimError::UnknownEnv { id: "dmc/x".into(), suggestions: vec!["dmc/y".into()] };
        let status = to_status(unknown);
        assert_eq!(status.code(), Code::NotFound);
        assert!(status.message().contains("did you mean dmc/y"));
        assert_eq!(to_status(SimError::InvalidArgument("bad".into())).code(), Code::InvalidArgument);
        assert_eq!(to_status(SimError::LimitExceeded("full".into())).code(), Code::ResourceExhausted);
        assert_eq!(to_status(SimError::ShuttingDown).code(), Code::Unavailable);
        let augment = radserve_augment::Pipeline::parse("crpo").unwrap_err();
        let status = replay_status(ReplayError::Augment(augment));
        assert_eq!(status.code(), Code::InvalidArgument);
        assert!(status.message().contains("did you mean \"crop\""), "{}", status.message());
    }
}
