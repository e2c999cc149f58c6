//! Produces augmented minibatches ahead of the learner, on a thread of its own. Each sample's stacks
//! are gathered from the frame store into per-thread scratch (reused) and augmented straight into
//! the batch, in parallel over the batch. A batch's buffers then move to the transport, which sends
//! them without copying, so each batch is a fresh allocation made on this thread.

use std::cell::RefCell;
use std::sync::{Arc, RwLock};
use std::time::Duration;

use radserve_augment::{Draws, FrameShape, ImagePlan, Pipeline, Sharing, StatePlan, View};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::buffer::{ReplayBuffer, TransitionMetadata, TransitionRef};
use crate::error::{ReplayError, Result};

/// What one observation is, for choosing the augmentation plan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObservationFormat {
    /// uint8 frame stacks `[frames * channels, height, width]`.
    Image(FrameShape),
    /// float32 vectors of this many elements (the whole stack).
    State(usize),
}

/// How a stream samples and augments.
#[derive(Clone, Debug)]
pub struct SampleSpec {
    pub batch_size: usize,
    pub pipeline: Pipeline,
    pub sharing: Sharing,
    pub seed: u64,
    /// Batches produced ahead and waiting (1..=64).
    pub prefetch: usize,
    /// Sampling waits until the buffer holds this many transitions (at least one batch's worth of
    /// distinct draws is not required: sampling is with replacement).
    pub min_size: usize,
    /// When set, sampling waits while samples would exceed `samples_per_insert * inserts +
    /// error_buffer` (Reverb's SampleToInsertRatio limiter).
    pub samples_per_insert: Option<f64>,
    pub error_buffer: f64,
    /// Stop after this many batches (none: until the client leaves).
    pub max_batches: Option<u64>,
}

/// One augmented minibatch.
#[derive(Debug, Default)]
pub struct Batch {
    /// 0, 1, 2... in the order produced.
    pub index: u64,
    pub len: usize,
    /// Shape of one augmented observation.
    pub obs_shape: Vec<usize>,
    /// Observations are float32 state vectors (little-endian bytes), not uint8 images.
    pub obs_float32: bool,
    /// `uint8` for images, float32 bytes (little-endian) for states.
    pub obs: Vec<u8>,
    pub next_obs: Vec<u8>,
    pub metadata: TransitionMetadata,
    refs: Vec<TransitionRef>,
}

enum Plan {
    Image(ImagePlan),
    State(StatePlan),
}

thread_local! {
    static STACK: RefCell<Vec<u8>> = RefCell::default();
}

/// A checked stream configuration, ready to start.
pub struct Producer {
    buffer: Arc<RwLock<ReplayBuffer>>,
    spec: SampleSpec,
    plan: Plan,
    obs_shape: Vec<usize>,
    obs_bytes: usize,
}

impl Producer {
    /// Check `spec` against the buffer and the observation before anything starts.
    pub fn new(buffer: Arc<RwLock<ReplayBuffer>>, format: ObservationFormat, spec: SampleSpec) -> Result<Self> {
        let capacity = buffer.read().expect("replay lock").layout().capacity;
        let invalid = |message: String| Err(ReplayError::InvalidArgument(message));
        if spec.batch_size == 0 || spec.batch_size > capacity {
            return invalid(format!(
                "batch_size must be between 1 and the replay capacity ({capacity}), got {}",
                spec.batch_size
            ));
        }
        if !(1..=64).contains(&spec.prefetch) {
            return invalid(format!("prefetch must be between 1 and 64 batches, got {}", spec.prefetch));
        }
        if spec.min_size > capacity {
            return invalid(format!(
                "min_size {} can never be reached: the replay capacity is {capacity}",
                spec.min_size
            ));
        }
        if let Some(ratio) = spec.samples_per_insert {
            if !(ratio.is_finite() && ratio > 0.0 && spec.error_buffer.is_finite() && spec.error_buffer >= 0.0) {
                return invalid(format!(
                    "samples_per_insert must be positive and error_buffer non-negative, got {ratio} and {}",
                    spec.error_buffer
                ));
            }
        }
        let (plan, obs_shape) = match format {
            ObservationFormat::Image(shape) => {
                let plan = ImagePlan::new(&spec.pipeline, shape)?;
                let out = plan.output_shape();
                (Plan::Image(plan), vec![out.planes(), out.height, out.width])
            }
            ObservationFormat::State(dim) => (Plan::State(StatePlan::new(&spec.pipeline, dim)?), vec![dim]),
        };
        let obs_bytes = match &plan {
            Plan::Image(plan) => plan.output_shape().sample_len(),
            Plan::State(plan) => plan.dim() * 4,
        };
        Ok(Self { buffer, spec, plan, obs_shape, obs_bytes })
    }

    pub fn obs_shape(&self) -> &[usize] {
        &self.obs_shape
    }

    /// Start producing on a thread of its own, augmenting on `pool`. Batches arrive on the returned
    /// receiver in order, at most `prefetch` ahead. Dropping the receiver stops the thread before
    /// its next batch.
    pub fn start(self, pool: Arc<rayon::ThreadPool>) -> tokio::sync::mpsc::Receiver<Result<Batch>> {
        let (ready_tx, ready_rx) = tokio::sync::mpsc::channel(self.spec.prefetch);
        std::thread::Builder::new()
            .name("radserve-sampler".into())
            .spawn(move || self.run(&pool, ready_tx))
            .expect("spawning a sampler thread");
        ready_rx
    }

    fn run(self, pool: &rayon::ThreadPool, ready: tokio::sync::mpsc::Sender<Result<Batch>>) {
        /// Counts this producer among the buffer's active ones until the thread ends.
        struct Active(Arc<std::sync::atomic::AtomicUsize>);
        impl Drop for Active {
            fn drop(&mut self) {
                self.0.fetch_sub(1, std::sync::atomic::Ordering::Relaxed);
            }
        }
        let counter = self.buffer.read().expect("replay lock").producer_counter();
        counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let _active = Active(counter);
        let mut rng = ChaCha8Rng::seed_from_u64(self.spec.seed);
        let mut index = 0u64;
        while self.spec.max_batches.is_none_or(|max| index < max) {
            if !self.wait_until_allowed(&ready) {
                return;
            }
            let mut batch = Batch { index, ..Batch::default() };
            if let Err(error) = self.fill(pool, &mut rng, &mut batch) {
                let _ = ready.blocking_send(Err(error));
                return;
            }
            if ready.blocking_send(Ok(batch)).is_err() {
                return; // the client left
            }
            index += 1;
        }
    }

    /// Wait for enough data and for the rate limiter; false when the client left meanwhile.
    fn wait_until_allowed(&self, ready: &tokio::sync::mpsc::Sender<Result<Batch>>) -> bool {
        loop {
            if ready.is_closed() {
                return false;
            }
            let (len, counters) = {
                let buffer = self.buffer.read().expect("replay lock");
                (buffer.len(), buffer.counters())
            };
            let enough = len >= self.spec.min_size.max(1);
            let within_rate = self.spec.samples_per_insert.is_none_or(|ratio| {
                (counters.samples + self.spec.batch_size as u64) as f64
                    <= ratio * counters.inserts as f64 + self.spec.error_buffer
            });
            if enough && within_rate {
                return true;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    fn fill(&self, pool: &rayon::ThreadPool, rng: &mut ChaCha8Rng, batch: &mut Batch) -> Result<()> {
        let size = self.spec.batch_size;
        batch.len = size;
        batch.obs_shape.clone_from(&self.obs_shape);
        batch.obs_float32 = matches!(self.plan, Plan::State(_));
        batch.obs.resize(size * self.obs_bytes, 0);
        batch.next_obs.resize(size * self.obs_bytes, 0);
        // Sampling bumps the counters, so it takes the write lock, briefly; the copies take the read lock.
        self.buffer.write().expect("replay lock").sample(size, rng, &mut batch.refs)?;
        let buffer = self.buffer.read().expect("replay lock");
        buffer.gather_metadata(&batch.refs, &mut batch.metadata);
        let draw_seed = self.spec.seed ^ batch.index.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let draws = Draws { seed: draw_seed, view: View::Obs, sharing: self.spec.sharing };
        let stack_bytes = buffer.layout().frame_stack * buffer.layout().frame_bytes;
        let refs = &batch.refs;
        match &self.plan {
            Plan::Image(plan) => pool.install(|| {
                for (view, out) in [(View::Obs, &mut batch.obs), (View::NextObs, &mut batch.next_obs)] {
                    let draws = draws.with_view(view);
                    out.par_chunks_mut(self.obs_bytes).enumerate().for_each(|(sample, dst)| {
                        let params = plan.draw(&draws, sample as u64);
                        STACK.with(|stack| {
                            let mut stack = stack.borrow_mut();
                            stack.resize(stack_bytes, 0);
                            buffer.copy_observation(refs[sample], view == View::NextObs, &mut stack);
                            plan.apply_sample(&stack, dst, &params);
                        });
                    });
                }
            }),
            Plan::State(plan) => {
                for (view, out) in [(View::Obs, &mut batch.obs), (View::NextObs, &mut batch.next_obs)] {
                    for (sample, dst) in out.chunks_exact_mut(self.obs_bytes).enumerate() {
                        buffer.copy_observation(refs[sample], view == View::NextObs, dst);
                    }
                    let values: Vec<f32> =
                        out.chunks_exact(4).map(|bytes| f32::from_le_bytes(bytes.try_into().unwrap())).collect();
                    let mut augmented = vec![0.0f32; values.len()];
                    plan.apply(&values, &mut augmented, &draws.with_view(view))?;
                    for (bytes, value) in out.chunks_exact_mut(4).zip(&augmented) {
                        bytes.copy_from_slice(&value.to_le_bytes());
                    }
                }
            }
        }
        Ok(())
    }
}
