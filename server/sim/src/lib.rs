//! radserve's simulator core: worker processes embedding CPython (the only crate that touches Python),
//! environment adapters for dm_control, gymnasium and ProcGen, and vectorized sessions with frame
//! stacking and same-step autoreset. No transport here: the service crate maps this onto gRPC.

pub mod bounds;
pub mod budget;
pub mod catalog;
pub mod error;
pub mod manager;
pub mod pool;
pub mod protocol;
pub mod session;
pub mod shm;
pub mod space;
pub mod worker;

pub use catalog::{EnvId, EnvNames, Family, OptionValue, Options};
pub use error::SimError;
pub use manager::{
    BufferRequest, CatalogEntry, LeaseHold, Limits, ReplayInfo, ReplaySource, SessionExtras, SessionInfo, SessionManager, SessionSummary,
};
pub use pool::{WorkerLauncher, WorkerPool};
pub use session::{EpisodeEnd, StepOutcome};
pub use space::{DType, Space};
pub use worker::{run_worker, GlBackend, WorkerArgs};
