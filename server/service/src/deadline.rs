//! Client deadlines: a reset or step runs to its end once it reached the simulators, whatever the
//! client's deadline; what the deadline still prevents is sending a request that waited for its
//! session past it.

use std::time::{Duration, Instant};

use tonic::Request;

use crate::error::{Result as ServiceResult, ServiceError};

/// When the client stops waiting, from its `grpc-timeout` header (gRPC over HTTP/2: an ASCII
/// integer of at most 8 digits and a unit, H M S m u n), measured from now.
pub fn client_deadline<T>(request: &Request<T>) -> Option<Instant> {
    let value = request.metadata().get("grpc-timeout")?.to_str().ok()?;
    let (digits, unit) = value.split_at(value.len().checked_sub(1)?);
    if digits.is_empty() || digits.len() > 8 {
        return None;
    }
    let amount: u64 = digits.parse().ok()?;
    let timeout = match unit {
        "H" => Duration::from_secs(amount.checked_mul(3600)?),
        "M" => Duration::from_secs(amount.checked_mul(60)?),
        "S" => Duration::from_secs(amount),
        "m" => Duration::from_millis(amount),
        "u" => Duration::from_micros(amount),
        "n" => Duration::from_nanos(amount),
        _ => return None,
    };
    Instant::now().checked_add(timeout)
}

/// Refuses a request whose client deadline passed while it waited for its session.
pub(crate) fn check_deadline(deadline: Option<Instant>, what: &str) -> ServiceResult<()> {
    match deadline {
        Some(deadline) if Instant::now() >= deadline => Err(ServiceError::TooLate(format!(
            "the {what} waited for the session (another call on it was running) past the client's deadline; it was \
             not sent to the simulators, and the session is as it was"
        ))),
        _ => Ok(()),
    }
}

/// Runs `work` on a task of its own and waits for it: dropping the caller's future (tonic does when
/// the client's deadline passes or the client leaves) does not stop `work` halfway.
pub(crate) async fn run_to_end<T: Send + 'static>(
    work: impl std::future::Future<Output = ServiceResult<T>> + Send + 'static,
) -> ServiceResult<T> {
    tokio::spawn(work).await.unwrap_or_else(|error| Err(ServiceError::Internal(format!("the call's task failed: {error}"))))
}
