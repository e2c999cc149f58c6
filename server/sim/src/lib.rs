//! radserve's simulators: worker processes that embed CPython (the only crate that touches Python)
//! and host environment adapters for dm_control, gymnasium and ProcGen. [`WorkerPool`] is the core's
//! [`radserve_core::Simulators`]: it places a session's envs in groups on the least loaded workers,
//! shares each group's frame memory with its worker, and rebuilds the groups of a worker that died.

pub mod groups;
pub mod pixels;
pub mod pool;
pub mod protocol;
pub mod worker;

pub use pool::{WorkerLauncher, WorkerPool};
pub use worker::{run_worker, GlBackend, WorkerArgs, WorkerError};
