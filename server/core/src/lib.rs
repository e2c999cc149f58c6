//! radserve's application core: sessions of vectorized environments with frame stacking, same-step
//! autoreset, evaluation views and replay recording; the server's limits and memory budget; the
//! environment catalog. Simulators are reached through the [`Simulators`] trait, so nothing here
//! links Python: `radserve-sim` implements it with worker processes, [`fake`] with plain Rust for
//! tests. No transport either: `radserve-service` maps this onto gRPC.

pub mod actions;
pub mod actor;
pub mod bounds;
pub mod budget;
pub mod catalog;
pub mod error;
#[cfg(any(test, feature = "testing"))]
pub mod fake;
pub mod infos;
pub mod manager;
pub mod metrics;
pub mod principal;
pub mod session;
pub mod simulators;
pub mod space;
#[cfg(test)]
mod test_support;

pub use catalog::{EnvId, EnvNames, Family, OptionValue, Options};
pub use error::CoreError;
pub use manager::{
    ActingConfig, ActingRequest, ActingState, ActingStatus, LoadedPolicy, DEFAULT_POLICY_MEMORY_BYTES,
    BufferRequest, CatalogEntry, LeaseHold, Limits, OnBadSnapshot, Progress, ReplayConfig, ReplayInfo, ReplaySource, SessionExtras,
    SessionInfo, SessionManager, SessionSummary, SnapshotInfo, MAX_NAME_BYTES,
};
pub use principal::{Principal, PrincipalLimits, Role};
pub use infos::{InfoColumn, InfoKind, Infos};
pub use session::{AutoresetMode, EpisodeEnd, ResetSpec, StepOutcome};
pub use simulators::{EnvGroup, EnvSpec, FrameLayout, PendingStep, SimulatorError, Simulators, StepResult};
pub use space::{DType, Space};
