//! radserve's replay buffers and minibatch producer: no tonic, no Python.
//!
//! Sessions record every step into a [`ReplayBuffer`] that stores each frame once; a [`Producer`]
//! samples it, rebuilds the frame stacks and augments them with `radserve-augment`, ahead of the
//! learner, into reused buffers or into a [`SharedRing`] that a learner on the same host maps.

mod buffer;
mod delivery;
mod error;
mod priority;
mod producer;
mod rate_limiter;
mod sequence;
mod shared;
pub mod snapshot;

pub use buffer::{
    check_capacity, ActedBy, BufferKind, ProducerPermit, RecordedStep, ReplayBuffer, ReplayCounters, ReplayLayout, Returns,
    TransitionMetadata, TransitionRef, Window, KEY_FRAME_BITS, MAX_CAPACITY, MAX_N_STEP, MIN_BYTES_PER_TRANSITION, NO_POLICY,
};
pub use delivery::{HeldSlots, InFlight};
pub use error::{ReplayError, Result};
pub use producer::{
    Batch, ObservationFormat, Output, Producer, Recycler, SampleSpec, Source, ViewData, ViewSpec, MAX_BATCH_BYTES, MAX_VIEWS,
    MAX_VIEW_NAME, RESERVED_FIELDS,
};
pub use priority::{
    importance_weights, priority_memory_bytes, Prioritized, PriorityUpdate, SumTree, INITIAL_PRIORITY, MAX_EXPONENTS, MAX_PRIORITY_UPDATES,
};
pub use rate_limiter::{Activity, Occupancy, RateLimiter};
pub use sequence::{Boundary, Sequence, MAX_SEQUENCE_LENGTH};
pub use shared::{SharedRing, Slot, SHARED_HEADER_BYTES, SHARED_MAGIC};
