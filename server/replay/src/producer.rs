//! Produces augmented minibatches ahead of the learner, on a thread of its own. Each sample's stacks
//! are gathered from the frame store into per-thread scratch (reused) and augmented straight into
//! the batch, in parallel over the batch. The batch's observations go either into heap buffers that
//! move to the transport (which sends them without copying and hands them back for reuse) or into a
//! slot of a shared-memory ring that a learner on the same host reads in place.

use std::cell::RefCell;
use std::ops::Range;
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

use radserve_augment::{Draws, FrameShape, ImagePlan, Pipeline, Sharing, StatePlan, TransitionPart};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::buffer::{BufferKind, ProducerPermit, ReplayBuffer, Returns, TransitionMetadata, TransitionRef};
use crate::error::{ReplayError, Result};
use crate::priority::{importance_weights, Prioritized};
use crate::rate_limiter::{Occupancy, RateLimiter};
use crate::sequence::Sequence;
use crate::shared::{SharedRing, Slot};

/// The largest batch of observations a stream may produce (1 GiB): 512 translated 108x108 stacks with
/// their next observations take 107 MB.
pub const MAX_BATCH_BYTES: usize = 1 << 30;

/// How long the augmentation pool works on one stream's batch before it takes a job another stream
/// queued meanwhile. A batch is made in chunks sized to take about this long (measured as it goes:
/// the first chunk has `FIRST_CHUNK` samples), so another stream's batch waits for one chunk, never
/// for all of this batch, and a stream whose client left stops within one chunk. Cheap pipelines
/// get large chunks: splitting a crop batch into 32-sample chunks cost a quarter of its rate here
/// (idle pool threads wake for every chunk; bench/fairness.py).
const TURN: Duration = Duration::from_millis(10);
const FIRST_CHUNK: usize = 64;
const MIN_CHUNK: usize = 4;
/// How often a stream waiting for transitions looks at whether its client left.
const LEFT_CHECK: Duration = Duration::from_millis(20);

/// Runs `work` over `0..total` samples in chunks that each take about [`TURN`], on a thread of the
/// augmentation pool; between two chunks it stops if the client left, else runs one job other
/// streams queued (rayon's `yield_now`).
fn in_turns(total: usize, keep_going: &(dyn Fn() -> bool + Sync), mut work: impl FnMut(Range<usize>)) -> Result<()> {
    let (mut start, mut size) = (0, FIRST_CHUNK);
    while start < total {
        if start > 0 {
            if !keep_going() {
                return Err(ReplayError::Cancelled);
            }
            rayon::yield_now();
        }
        let end = (start + size).min(total);
        let began = Instant::now();
        work(start..end);
        let per_sample = began.elapsed().as_secs_f64() / (end - start) as f64;
        size = if per_sample > 0.0 { ((TURN.as_secs_f64() / per_sample) as usize).max(MIN_CHUNK) } else { total };
        start = end;
    }
    Ok(())
}

/// What one observation is, for choosing the augmentation plan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObservationFormat {
    /// uint8 frame stacks `[frames * channels, height, width]`.
    Image(FrameShape),
    /// float32 vectors of this many elements (the whole stack).
    State(usize),
}

/// Where a stream's transitions come from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Source {
    /// Uniform with replacement from a replay buffer.
    #[default]
    Replay,
    /// Every transition of the last rollout once per epoch, in a fresh random order each epoch.
    /// With `per_env_draws`, augmentation parameters are drawn once per environment and held for
    /// the whole rollout (the paper's PPO); otherwise once per sample.
    Rollout { epochs: usize, per_env_draws: bool },
}

/// The most named views one request may ask for (DrQ asks for four, CURL and SVEA for three).
pub const MAX_VIEWS: usize = 8;

/// The longest view name.
pub const MAX_VIEW_NAME: usize = 32;

/// Names a view may not take: the batch's other fields (and the Python client's `server`).
pub const RESERVED_FIELDS: [&str; 20] = [
    "action", "reward", "discount", "terminated", "truncated", "env_index", "step_index", "policy_version", "t",
    "log_prob", "value", "key", "probability", "table_size", "weight", "server", "is_first", "is_last", "is_terminal",
    "mask",
];

/// One named output of a batch: the observation or the next observation of each sample, through a
/// pipeline of its own. Views with the same `draws` label share their random parameters stage by
/// stage (SVEA's strongly augmented view beside its shifted one); the others draw independently.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewSpec {
    pub name: String,
    pub of: TransitionPart,
    pub pipeline: Pipeline,
    pub draws: Option<String>,
}

impl ViewSpec {
    /// A view with draws of its own.
    pub fn new(name: &str, of: TransitionPart, pipeline: Pipeline) -> ViewSpec {
        ViewSpec { name: name.to_owned(), of, pipeline, draws: None }
    }

    fn check_name(name: &str) -> Result<()> {
        let plain = !name.is_empty()
            && name.len() <= MAX_VIEW_NAME
            && name.starts_with(|c: char| c.is_ascii_lowercase() || c == '_')
            && name.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_');
        if !plain {
            return Err(ReplayError::InvalidArgument(format!(
                "view names are lowercase names of at most {MAX_VIEW_NAME} characters (letters, digits, '_'), such as \
                 \"obs_aug\"; got {:?}",
                name.chars().take(MAX_VIEW_NAME + 8).collect::<String>()
            )));
        }
        if RESERVED_FIELDS.contains(&name) {
            return Err(ReplayError::InvalidArgument(format!(
                "view name {name:?} is a field every batch has; name views anything but {}",
                RESERVED_FIELDS.join(", ")
            )));
        }
        Ok(())
    }
}

/// How a stream samples and augments.
#[derive(Clone, Debug)]
pub struct SampleSpec {
    pub source: Source,
    pub batch_size: usize,
    /// Without views: send next_obs too (off-policy learners need it; PPO does not).
    pub include_next_obs: bool,
    /// Without views: the pipeline of obs and next_obs, which share draws as `sharing` says.
    pub pipeline: Pipeline,
    pub sharing: Sharing,
    /// Named outputs instead of obs and next_obs (empty: obs, and next_obs with
    /// `include_next_obs`, through `pipeline`).
    pub views: Vec<ViewSpec>,
    /// n-step returns: the batch's reward sums up to n rewards and it carries `discount` (none: the
    /// transition's own reward, no discount).
    pub returns: Option<Returns>,
    /// Proportional prioritized sampling (none: uniform): replay only.
    pub prioritized: Option<Prioritized>,
    /// Sequences of consecutive steps instead of single transitions (replay only): every field
    /// gains a time axis after the batch's.
    pub sequence: Option<Sequence>,
    pub seed: u64,
    /// Batches produced ahead and waiting (1..=64).
    pub prefetch: usize,
    /// Sampling waits until the buffer holds this many transitions (at least one batch's worth of
    /// distinct draws is not required: sampling is with replacement).
    pub min_size: usize,
    /// When set, sampling keeps to this many samples per insert after `min_size`, within
    /// `error_buffer` (Reverb's SampleToInsertRatio: see [`RateLimiter`]).
    pub samples_per_insert: Option<f64>,
    pub error_buffer: f64,
    /// Stop after this many batches (none: until the client leaves).
    pub max_batches: Option<u64>,
}

impl SampleSpec {
    /// Batches produced ahead when a request does not say (the wire's 0).
    pub const DEFAULT_PREFETCH: usize = 2;
    /// Passes over a rollout when a request does not say (the wire's 0). A spec itself must say:
    /// `Producer::new` refuses 0 epochs from a caller that builds specs directly.
    pub const DEFAULT_EPOCHS: usize = 1;
}

/// Where the transport returns observation buffers it has finished sending.
pub type Recycler = std::sync::mpsc::Sender<Vec<u8>>;

/// Where a producer writes the observations of its batches.
pub enum Output {
    /// Heap buffers in `Batch::obs` / `Batch::next_obs`, reused once returned through the Recycler.
    Heap,
    /// A slot of this ring per batch (`Batch::slot`), waited for when all are taken.
    Shared(Arc<SharedRing>),
}

/// Observation buffers returned by the transport, waiting to be reused.
struct Spare {
    returned: std::sync::mpsc::Receiver<Vec<u8>>,
    buffers: Vec<Vec<u8>>,
}

impl Spare {
    /// A buffer of exactly `len` bytes: a returned one if there is one (every byte of it gets
    /// overwritten), else a fresh one from calloc, whose pages the kernel zeroes on first touch.
    fn take(&mut self, len: usize) -> Vec<u8> {
        self.buffers.extend(self.returned.try_iter());
        match self.buffers.iter().position(|buffer| buffer.len() == len) {
            Some(position) => self.buffers.swap_remove(position),
            None => vec![0; len],
        }
    }
}

/// One view of a batch: its observations, augmented.
#[derive(Debug, Default)]
pub struct ViewData {
    pub name: String,
    /// Shape of one augmented observation.
    pub shape: Vec<usize>,
    /// `uint8` for images, float32 bytes (little-endian) for states; empty with shared output (the
    /// batch's slot holds them, in the view's region).
    pub data: Vec<u8>,
}

/// One augmented minibatch.
#[derive(Debug, Default)]
pub struct Batch {
    /// 0, 1, 2... in the order produced.
    pub index: u64,
    pub len: usize,
    /// Observations are float32 state vectors (little-endian bytes), not uint8 images.
    pub obs_float32: bool,
    /// The observations, one per view in the request's order (obs, then next_obs when the request
    /// names no views).
    pub views: Vec<ViewData>,
    pub metadata: TransitionMetadata,
    /// The batch carries n-step returns: `metadata.discounts` is part of it.
    pub has_discount: bool,
    /// The batch was drawn by priority: `metadata.probabilities` and `metadata.weights` are part
    /// of it.
    pub prioritized: bool,
    /// In a prioritized batch: the transitions that could be drawn (the N of the importance
    /// weights).
    pub table_size: usize,
    /// A sequence batch: `len` sequences of this many steps; every field is `[len, steps, ...]`
    /// (its views' data and metadata rows in that order) and the metadata's sequence flags are
    /// part of it.
    pub sequence_steps: Option<usize>,
    /// For rollouts: each transition's step within the rollout (0 the oldest).
    pub rollout_t: Option<Vec<u32>>,
    /// With shared output: the slot holding the views, region i view i; their `data` stays empty.
    pub slot: Option<Slot>,
    refs: Vec<TransitionRef>,
}

impl Batch {
    /// The view named `name`.
    pub fn view(&self, name: &str) -> Option<&ViewData> {
        self.views.iter().find(|view| view.name == name)
    }

    /// The leading dimensions of every field: `[len]`, or `[len, steps]` for sequences.
    pub fn lead_dims(&self) -> Vec<usize> {
        std::iter::once(self.len).chain(self.sequence_steps).collect()
    }
}

/// Each sample of `samples`' destination in every view: the views' outputs cut into pieces of
/// `bytes[view]` per sample (a sequence's sample is all its steps).
fn destinations<'a>(outputs: &'a mut [&mut [u8]], bytes: &[usize], samples: Range<usize>) -> Vec<Vec<&'a mut [u8]>> {
    let mut destinations: Vec<Vec<&mut [u8]>> = (0..samples.len()).map(|_| Vec::with_capacity(bytes.len())).collect();
    for (output, &bytes) in outputs.iter_mut().zip(bytes) {
        let part = &mut output[samples.start * bytes..samples.end * bytes];
        for (destination, chunk) in destinations.iter_mut().zip(part.chunks_exact_mut(bytes)) {
            destination.push(chunk);
        }
    }
    destinations
}

/// Where `fill` gets the memory for a batch's observations.
enum Destination {
    Heap(Spare),
    Shared(Arc<SharedRing>),
}

enum Plan {
    Image(ImagePlan),
    State(StatePlan),
}

/// A view checked against the observation: its plan, its output and its draws.
struct ViewPlan {
    name: String,
    of: TransitionPart,
    plan: Plan,
    shape: Vec<usize>,
    /// Bytes of one augmented observation.
    bytes: usize,
    /// The draws' part, sharing and stream; each batch sets the seed.
    draws: Draws,
}

/// Where a sample's stacks lie in the frames copied for it.
#[derive(Clone, Copy)]
enum Frames {
    /// `frame_stack + 1` frames: obs from the first, next_obs from the second (one step).
    Joined,
    /// Two stacks, obs then next_obs (n steps, where the two need not overlap).
    Split,
    /// The observation's stack only.
    ObsOnly,
    /// The next observation's stack only.
    NextOnly,
}

thread_local! {
    static STACK: RefCell<Vec<u8>> = RefCell::default();
}

/// A checked stream configuration, ready to start.
pub struct Producer {
    buffer: Arc<RwLock<ReplayBuffer>>,
    spec: SampleSpec,
    /// Reverb's rate limiter, when the spec sets samples_per_insert.
    limiter: Option<RateLimiter>,
    views: Vec<ViewPlan>,
    frames: Frames,
    /// Steps summed per transition (1 without n-step returns).
    n_step: usize,
    /// This stream's place among the buffer's producers, reserved at admission.
    permit: Option<ProducerPermit>,
    /// Rows per sample: the sequence's steps (1 for transitions).
    steps: usize,
    /// The buffer's insert count when a sequence stream last found no window to start: it waits
    /// for the next insert rather than drawing again in vain (`u64::MAX`: it found one).
    no_window_at: std::sync::atomic::AtomicU64,
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
        if let Some(sequence) = spec.sequence {
            Self::check_sequence(&spec, &sequence, &buffer.read().expect("replay lock"))?;
        }
        let kind = buffer.read().expect("replay lock").layout().kind;
        match (spec.source, kind) {
            (Source::Replay, BufferKind::Replay) => {}
            (Source::Rollout { epochs, .. }, BufferKind::Rollout { steps }) => {
                if epochs == 0 {
                    return invalid("epochs must be at least 1".into());
                }
                // Refused now, before the stream starts, if the rollout is not complete.
                buffer.read().expect("replay lock").rollout(steps)?;
            }
            (Source::Rollout { .. }, BufferKind::Replay) => {
                return Err(ReplayError::FailedPrecondition(
                    "this session keeps a replay buffer, not a rollout: sample it with the replay source".into(),
                ))
            }
            (Source::Replay, BufferKind::Rollout { .. }) => {
                return Err(ReplayError::FailedPrecondition(
                    "this session keeps a rollout, not a replay buffer: sample it with the rollout source".into(),
                ))
            }
        }
        let limiter = match spec.samples_per_insert {
            Some(ratio) => Some(RateLimiter::new(spec.min_size as u64, ratio, spec.error_buffer).map_err(ReplayError::InvalidArgument)?),
            None => None,
        };
        if spec.returns.is_some() && spec.source != Source::Replay {
            return invalid(
                "n_step and discount apply to replay: a rollout's returns are the learner's (GAE over the rollout)".into(),
            );
        }
        if spec.prioritized.is_some() && spec.source != Source::Replay {
            return invalid("prioritized sampling applies to replay: a rollout visits each of its transitions once per epoch".into());
        }
        let views = Self::plan_views(&spec, format)?;
        let n_step = spec.returns.map_or(1, |returns| returns.n_step);
        let with_obs = views.iter().any(|view| view.of == TransitionPart::Obs);
        let with_next = views.iter().any(|view| view.of == TransitionPart::NextObs);
        let frames = match (with_obs, with_next) {
            (true, true) if n_step == 1 => Frames::Joined,
            (true, true) => Frames::Split,
            (false, true) => Frames::NextOnly,
            _ => Frames::ObsOnly,
        };
        let steps = spec.sequence.map_or(1, |sequence| sequence.length);
        let sample_bytes = views.iter().fold(0usize, |sum, view| sum.saturating_add(view.bytes)).saturating_mul(steps);
        let batch_bytes = spec.batch_size.saturating_mul(sample_bytes);
        if batch_bytes > MAX_BATCH_BYTES {
            let names: Vec<&str> = views.iter().map(|view| view.name.as_str()).collect();
            let what = if steps > 1 { format!("sequences of {steps} steps") } else { "samples".to_owned() };
            return invalid(format!(
                "a batch of {} {what} of {sample_bytes} bytes (views {}) is {batch_bytes} bytes; the most allowed is \
                 {MAX_BATCH_BYTES} (use a smaller batch_size, fewer views, shorter sequences or a smaller augmentation \
                 output)",
                spec.batch_size,
                names.join(", "),
            ));
        }
        Ok(Self { buffer, spec, limiter, views, frames, n_step, permit: None, steps, no_window_at: u64::MAX.into() })
    }

    /// What sequences combine with: replay, views of the observation, per-step discounts; not
    /// n-step returns (a sequence carries every step's reward: the learner sums them, as R2D2
    /// does), next observations (the next step is the next observation) or priorities (yet).
    fn check_sequence(spec: &SampleSpec, sequence: &Sequence, buffer: &ReplayBuffer) -> Result<()> {
        let invalid = |message: String| Err(ReplayError::InvalidArgument(message));
        if spec.source != Source::Replay {
            return invalid(
                "sequences sample replay: a rollout is served whole, in its (t, env) order, per epoch".into(),
            );
        }
        if spec.returns.is_some_and(|returns| returns.n_step > 1) {
            return invalid(
                "sequences carry every step's reward and discount; n_step returns apply to single transitions (sum \
                 them over the sequence, as R2D2 does)"
                    .into(),
            );
        }
        if spec.prioritized.is_some() {
            return invalid(
                "prioritized sampling draws single transitions; sequences are drawn uniformly (sampler \
                 SAMPLER_UNIFORM)"
                    .into(),
            );
        }
        let next = if spec.views.is_empty() {
            spec.include_next_obs
        } else {
            spec.views.iter().any(|view| view.of == TransitionPart::NextObs)
        };
        if next {
            return invalid(
                "a sequence's next observation is its next step: name views of obs only, and leave include_next_obs \
                 off"
                .into(),
            );
        }
        let layout = buffer.layout();
        let per_env = layout.capacity / layout.num_envs;
        if sequence.length + 1 > per_env {
            return invalid(format!(
                "a sequence of {} steps needs {} frames of one env held at once; the replay keeps {per_env} transitions \
                 per env (capacity {} over {} envs)",
                sequence.length,
                sequence.length + 1,
                layout.capacity,
                layout.num_envs
            ));
        }
        Ok(())
    }

    /// The request's views checked against the observation; without named views, obs (and
    /// next_obs) through the request's pipeline, drawn as `sharing` says.
    fn plan_views(spec: &SampleSpec, format: ObservationFormat) -> Result<Vec<ViewPlan>> {
        let invalid = |message: String| Err(ReplayError::InvalidArgument(message));
        if spec.views.len() > MAX_VIEWS {
            return invalid(format!("a request names at most {MAX_VIEWS} views, got {}", spec.views.len()));
        }
        let plan = |pipeline: &Pipeline| -> std::result::Result<(Plan, Vec<usize>, usize), radserve_augment::AugmentError> {
            Ok(match format {
                ObservationFormat::Image(shape) => {
                    let plan = ImagePlan::new(pipeline, shape)?;
                    let out = plan.output_shape();
                    (Plan::Image(plan), vec![out.planes(), out.height, out.width], out.sample_len())
                }
                ObservationFormat::State(dim) => (Plan::State(StatePlan::new(pipeline, dim)?), vec![dim], dim * 4),
            })
        };
        let mut views = Vec::new();
        if spec.views.is_empty() {
            let parts: &[(&str, TransitionPart)] = if spec.include_next_obs {
                &[("obs", TransitionPart::Obs), ("next_obs", TransitionPart::NextObs)]
            } else {
                &[("obs", TransitionPart::Obs)]
            };
            for &(name, of) in parts {
                let (plan, shape, bytes) = plan(&spec.pipeline).map_err(ReplayError::from)?;
                let draws = Draws { seed: 0, part: of, sharing: spec.sharing, stream: 0 };
                views.push(ViewPlan { name: name.into(), of, plan, shape, bytes, draws });
            }
            return Ok(views);
        }
        for (index, view) in spec.views.iter().enumerate() {
            ViewSpec::check_name(&view.name)?;
            if spec.views[..index].iter().any(|earlier| earlier.name == view.name) {
                return invalid(format!("view {:?} is named twice; each view needs a name of its own", view.name));
            }
            let (plan, shape, bytes) = plan(&view.pipeline)
                .map_err(|error| ReplayError::InvalidArgument(format!("view {:?}: {error}", view.name)))?;
            // Views draw from the stream of the first view with their label (1 + its index), each
            // as if it were the observation: a shared stream shares every stage.
            let stream = match &view.draws {
                Some(label) => spec.views.iter().position(|other| other.draws.as_ref() == Some(label)).unwrap_or(index),
                None => index,
            };
            let draws = Draws { seed: 0, part: TransitionPart::Obs, sharing: Sharing::Shared, stream: 1 + stream as u32 };
            views.push(ViewPlan { name: view.name.clone(), of: view.of, plan, shape, bytes, draws });
        }
        Ok(views)
    }

    /// Run under `permit`, the place reserved for this stream when it was admitted (without one, the
    /// producer counts itself when it starts, unlimited).
    pub fn with_permit(mut self, permit: ProducerPermit) -> Self {
        self.permit = Some(permit);
        self
    }

    /// The names of the batch's views and the shape of one of each view's observations.
    pub fn view_shapes(&self) -> Vec<(&str, &[usize])> {
        self.views.iter().map(|view| (view.name.as_str(), view.shape.as_slice())).collect()
    }

    /// Bytes of each view's observations in one batch: the regions of a shared slot.
    pub fn region_bytes(&self) -> Vec<usize> {
        self.views.iter().map(|view| self.spec.batch_size * self.steps * view.bytes).collect()
    }

    /// Batches produced ahead of the learner.
    pub fn prefetch(&self) -> usize {
        self.spec.prefetch
    }

    /// Bytes the stream may hold at once, whichever the output: the observations of `prefetch`
    /// batches ready, one being filled and one with the transport or the learner. A prioritized
    /// stream also counts what its sampling may add to the buffer: the priorities and its
    /// exponent's sum tree ([`crate::priority_memory_bytes`]).
    pub fn stream_memory_bytes(&self) -> u64 {
        let batches = ((self.spec.prefetch + 2) * self.region_bytes().iter().sum::<usize>()) as u64;
        let priorities = match self.spec.prioritized {
            Some(_) => {
                let layout = *self.buffer.read().expect("replay lock").layout();
                crate::priority::priority_memory_bytes(layout.num_envs * layout.slots_per_env())
            }
            None => 0,
        };
        batches + priorities
    }

    /// Start producing on a thread of its own, augmenting on `pool`. Batches arrive on the returned
    /// receiver in order, at most `prefetch` ahead. With heap output, observation buffers sent back
    /// on the returned sender once the transport is done with them are reused for later batches;
    /// with shared output, a batch's slot is reused once the transport drops the batch's `Slot`.
    /// Dropping the receiver stops the thread before its next batch.
    pub fn start(self, pool: Arc<rayon::ThreadPool>, output: Output) -> (tokio::sync::mpsc::Receiver<Result<Batch>>, Recycler) {
        let (ready_tx, ready_rx) = tokio::sync::mpsc::channel(self.spec.prefetch);
        let (recycle_tx, recycle_rx) = std::sync::mpsc::channel();
        let destination = match output {
            Output::Heap => Destination::Heap(Spare { returned: recycle_rx, buffers: Vec::new() }),
            Output::Shared(ring) => Destination::Shared(ring),
        };
        std::thread::Builder::new()
            .name("radserve-sampler".into())
            .spawn(move || self.run(&pool, ready_tx, destination))
            .expect("spawning a sampler thread");
        (ready_rx, recycle_tx)
    }

    fn run(self, pool: &rayon::ThreadPool, ready: tokio::sync::mpsc::Sender<Result<Batch>>, mut spare: Destination) {
        // Counts this producer among the buffer's active ones until the thread ends.
        let _permit = match &self.permit {
            Some(_) => None,
            None => self.buffer.read().expect("replay lock").admit_producer(usize::MAX),
        };
        let mut rng = ChaCha8Rng::seed_from_u64(self.spec.seed);
        match self.spec.source {
            Source::Replay => self.run_replay(pool, &ready, &mut rng, &mut spare),
            Source::Rollout { epochs, per_env_draws } => {
                self.run_rollout(pool, &ready, &mut rng, &mut spare, epochs, per_env_draws)
            }
        }
    }

    fn run_replay(
        &self,
        pool: &rayon::ThreadPool,
        ready: &tokio::sync::mpsc::Sender<Result<Batch>>,
        rng: &mut ChaCha8Rng,
        spare: &mut Destination,
    ) {
        // A prioritized stream holds its exponent's sum tree while it runs.
        let _exponent = match self.spec.prioritized {
            Some(prioritized) => match ExponentHeld::acquire(&self.buffer, prioritized.exponent) {
                Ok(held) => Some(held),
                Err(error) => {
                    let _ = ready.blocking_send(Err(error));
                    return;
                }
            },
            None => None,
        };
        let mut index = 0u64;
        while self.spec.max_batches.is_none_or(|max| index < max) {
            let mut batch = Batch { index, prioritized: self.spec.prioritized.is_some(), ..Batch::default() };
            // Checked again under the write lock that counts the samples, so that two streams on
            // one buffer cannot both take the limiter's last allowance.
            let (sampled, sampleable) = loop {
                if !self.wait_until_allowed(ready) {
                    return;
                }
                let mut buffer = self.buffer.write().expect("replay lock");
                if self.allowed(&buffer) {
                    let (count, n_step) = (self.spec.batch_size, self.n_step);
                    if let Some(sequence) = &self.spec.sequence {
                        match buffer.sample_sequences(count, sequence, rng, &mut batch.refs) {
                            Ok(true) => break (Ok(()), 0),
                            Ok(false) => {
                                self.no_window_at.store(buffer.counters().inserts, std::sync::atomic::Ordering::Relaxed);
                                continue;
                            }
                            Err(error) => break (Err(error), 0),
                        }
                    }
                    break match self.spec.prioritized {
                        Some(prioritized) => {
                            let probabilities = &mut batch.metadata.probabilities;
                            match buffer.sample_prioritized(count, n_step, prioritized.exponent, rng, &mut batch.refs, probabilities) {
                                Ok(sampleable) => (Ok(()), sampleable),
                                Err(error) => (Err(error), 0),
                            }
                        }
                        None => (buffer.sample_windows(count, n_step, rng, &mut batch.refs), 0),
                    };
                }
            };
            if !self.allocate(spare, &mut batch, self.spec.batch_size * self.steps, ready) {
                return;
            }
            let seed = self.spec.seed ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15);
            let keep_going = || !ready.is_closed();
            let filled = sampled.and_then(|()| match &self.spec.sequence {
                Some(sequence) => self.fill_sequences(pool, &mut batch, sequence, seed, &keep_going),
                None => self.fill(pool, &mut batch, seed, None, &keep_going),
            });
            if let Err(error) = filled {
                if error != ReplayError::Cancelled {
                    let _ = ready.blocking_send(Err(error));
                }
                return;
            }
            if let Some(prioritized) = self.spec.prioritized {
                batch.table_size = sampleable;
                let metadata = &mut batch.metadata;
                importance_weights(&metadata.probabilities, sampleable, prioritized.importance_exponent, &mut metadata.weights);
            }
            if ready.blocking_send(Ok(batch)).is_err() {
                return; // the client left
            }
            index += 1;
        }
    }

    fn run_rollout(
        &self,
        pool: &rayon::ThreadPool,
        ready: &tokio::sync::mpsc::Sender<Result<Batch>>,
        rng: &mut ChaCha8Rng,
        spare: &mut Destination,
        epochs: usize,
        per_env_draws: bool,
    ) {
        let BufferKind::Rollout { steps } = self.buffer.read().expect("replay lock").layout().kind else {
            unreachable!("checked in Producer::new")
        };
        let table = match self.buffer.read().expect("replay lock").rollout(steps) {
            Ok((table, _start)) => table,
            Err(error) => {
                let _ = ready.blocking_send(Err(error));
                return;
            }
        };
        let num_envs = table.len() / steps;
        let mut index = 0u64;
        for _ in 0..epochs {
            let mut order: Vec<usize> = (0..table.len()).collect();
            order.shuffle(rng);
            for chunk in order.chunks(self.spec.batch_size) {
                if self.spec.max_batches.is_some_and(|max| index >= max) || ready.is_closed() {
                    return;
                }
                let mut batch = Batch { index, ..Batch::default() };
                if !self.allocate(spare, &mut batch, chunk.len(), ready) {
                    return;
                }
                batch.refs = chunk.iter().map(|&position| table[position]).collect();
                batch.rollout_t = Some(chunk.iter().map(|&position| (position / num_envs) as u32).collect());
                self.buffer.write().expect("replay lock").count_samples(chunk.len());
                // Held per env: one seed for the whole stream, keyed by env; else per batch and sample.
                let (seed, keys) = if per_env_draws {
                    (self.spec.seed, Some(batch.refs.iter().map(|transition| transition.env as u64).collect::<Vec<_>>()))
                } else {
                    (self.spec.seed ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15), None)
                };
                if let Err(error) = self.fill(pool, &mut batch, seed, keys.as_deref(), &|| !ready.is_closed()) {
                    if error != ReplayError::Cancelled {
                        let _ = ready.blocking_send(Err(error));
                    }
                    return;
                }
                if ready.blocking_send(Ok(batch)).is_err() {
                    return;
                }
                index += 1;
            }
        }
    }

    /// Whether the buffer holds `min_size` transitions (with complete n-step windows) and the rate
    /// limiter lets a batch through.
    fn allowed(&self, buffer: &ReplayBuffer) -> bool {
        if self.no_window_at.load(std::sync::atomic::Ordering::Relaxed) == buffer.counters().inserts {
            return false;
        }
        let size = buffer.sampleable(self.n_step);
        match &self.limiter {
            Some(limiter) => limiter.can_sample(Occupancy::of(buffer.counters(), size), (self.spec.batch_size * self.steps) as u64),
            None => size >= self.spec.min_size.max(1),
        }
    }

    /// Waits, woken by the buffer's inserts and samples, until a batch is allowed; false when the
    /// client left meanwhile (looked at every [`LEFT_CHECK`]).
    fn wait_until_allowed(&self, ready: &tokio::sync::mpsc::Sender<Result<Batch>>) -> bool {
        let activity = self.buffer.read().expect("replay lock").activity();
        activity.wait_blocking(|| self.allowed(&self.buffer.read().expect("replay lock")), || !ready.is_closed(), LEFT_CHECK)
    }

    /// Memory for the observations of a batch of `size`: heap buffers, or a shared slot once one is
    /// free. False when the client left while waiting for a slot.
    fn allocate(
        &self,
        destination: &mut Destination,
        batch: &mut Batch,
        size: usize,
        ready: &tokio::sync::mpsc::Sender<Result<Batch>>,
    ) -> bool {
        match destination {
            Destination::Heap(spare) => {
                batch.views = self
                    .views
                    .iter()
                    .map(|view| ViewData { name: view.name.clone(), shape: view.shape.clone(), data: spare.take(size * view.bytes) })
                    .collect();
            }
            Destination::Shared(ring) => match ring.acquire(|| !ready.is_closed()) {
                Some(slot) => {
                    batch.slot = Some(slot);
                    batch.views = self
                        .views
                        .iter()
                        .map(|view| ViewData { name: view.name.clone(), shape: view.shape.clone(), data: Vec::new() })
                        .collect();
                }
                None => return false,
            },
        }
        true
    }

    /// Gather and augment the transitions in `batch.refs` into the observation memory `allocate`
    /// gave the batch; sample i draws with `keys[i]` (default i). The replay lock is never held while
    /// images are augmented: each turn (`in_turns`) reads its samples' metadata under one read lock,
    /// then each sample copies its frames under a read lock of its own and augments them without
    /// it, so a Step recording into the buffer waits for one sample's copy, not for a batch. A
    /// transition the buffer still holds does not change, nor do the later steps of its n-step
    /// window, so frames and metadata read under two locks agree; one it overwrote meanwhile (the
    /// session stepped past it in a small buffer) is drawn again from what the buffer holds then.
    fn fill(
        &self,
        pool: &rayon::ThreadPool,
        batch: &mut Batch,
        draw_seed: u64,
        keys: Option<&[u64]>,
        keep_going: &(dyn Fn() -> bool + Sync),
    ) -> Result<()> {
        let size = batch.refs.len();
        batch.len = size;
        batch.obs_float32 = self.views.first().is_some_and(|view| matches!(view.plan, Plan::State(_)));
        batch.has_discount = self.spec.returns.is_some();
        let draws: Vec<Draws> = self.views.iter().map(|view| Draws { seed: draw_seed, ..view.draws }).collect();
        let lens: Vec<usize> = self.views.iter().map(|view| size * view.bytes).collect();
        let mut outputs: Vec<&mut [u8]> = match &mut batch.slot {
            Some(slot) => slot.regions_mut(&lens),
            None => batch.views.iter_mut().zip(&lens).map(|(view, &len)| &mut view.data[..len]).collect(),
        };
        let returns = self.spec.returns;
        // Rollouts visit fixed (t, env) transitions; only replay samples are drawn again.
        let redraw = matches!(self.spec.source, Source::Replay);
        let n_step = self.n_step;
        let gather = |buffer: &ReplayBuffer, refs: &[TransitionRef], metadata: &mut TransitionMetadata, start: usize| {
            buffer.gather_metadata_at(refs, metadata, start);
            if let Some(returns) = returns {
                buffer.gather_returns_at(refs, returns, metadata, start);
            }
        };
        // A transition the buffer overwrote since it was drawn is replaced by a fresh draw (by
        // priority, with its probability, in a prioritized stream).
        let prioritized = self.spec.prioritized;
        let refresh = |buffer: &ReplayBuffer, sample: usize, refs: &mut [TransitionRef], metadata: &mut TransitionMetadata, rng: &mut ChaCha8Rng| {
            if !redraw || buffer.still_holds(refs[sample]) {
                return;
            }
            match prioritized {
                Some(prioritized) => {
                    if let Some((fresh, probability)) = buffer.draw_one_prioritized(n_step, prioritized.exponent, rng) {
                        refs[sample] = fresh;
                        metadata.probabilities[sample] = probability;
                    }
                }
                None => {
                    if let Some(fresh) = buffer.draw_one_window(n_step, rng) {
                        refs[sample] = fresh;
                    }
                }
            }
        };
        let mut rng = ChaCha8Rng::seed_from_u64(draw_seed ^ 0x5E_ED0F_D2A5);
        let (frame_bytes, stack_bytes) = {
            let buffer = self.buffer.read().expect("replay lock");
            let layout = buffer.layout();
            batch.metadata.resize(size, layout.action_bytes);
            (layout.frame_bytes, layout.frame_stack * layout.frame_bytes)
        };
        // Where a sample's two stacks lie in the frames copied for it.
        let (copied_bytes, obs_at, next_at) = match self.frames {
            // With both, stack + 1 frames serve both stacks (a third less reading).
            Frames::Joined => (stack_bytes + frame_bytes, 0, frame_bytes),
            Frames::Split => (2 * stack_bytes, 0, stack_bytes),
            Frames::ObsOnly | Frames::NextOnly => (stack_bytes, 0, 0),
        };
        let copy = |buffer: &ReplayBuffer, transition: TransitionRef, last_frame: u64, frames: &mut Vec<u8>| {
            frames.resize(copied_bytes, 0);
            match self.frames {
                Frames::Joined => buffer.copy_transition(transition, frames),
                Frames::Split => {
                    let (obs, next) = frames.split_at_mut(stack_bytes);
                    buffer.copy_observation(transition, false, obs);
                    buffer.copy_stack_ending(transition, last_frame, next);
                }
                Frames::ObsOnly => buffer.copy_observation(transition, false, frames),
                Frames::NextOnly => buffer.copy_stack_ending(transition, last_frame, frames),
            }
        };
        let stack_of = |of: TransitionPart| -> Range<usize> {
            let at = if of == TransitionPart::Obs { obs_at } else { next_at };
            at..at + stack_bytes
        };
        let (refs, metadata) = (&mut batch.refs, &mut batch.metadata);
        if self.views.iter().all(|view| matches!(view.plan, Plan::Image(_))) {
            let augment = |frames: &[u8], key: u64, outputs: Vec<&mut [u8]>| {
                for ((view, draws), dst) in self.views.iter().zip(&draws).zip(outputs) {
                    let Plan::Image(plan) = &view.plan else { unreachable!("checked above") };
                    plan.apply_sample(&frames[stack_of(view.of)], dst, &plan.draw(draws, key));
                }
            };
            let key = |sample: usize| keys.map_or(sample as u64, |keys| keys[sample]);
            let bytes: Vec<usize> = self.views.iter().map(|view| view.bytes).collect();
            pool.install(|| {
                in_turns(size, keep_going, |samples| {
                    {
                        let buffer = self.buffer.read().expect("replay lock");
                        for sample in samples.clone() {
                            refresh(&buffer, sample, refs, metadata, &mut rng);
                        }
                        gather(&buffer, &refs[samples.clone()], metadata, samples.start);
                    }
                    let stale = std::sync::Mutex::new(Vec::new());
                    {
                        let (refs, last_frames) = (&refs[..], &metadata.last_frames);
                        // Copied under a read lock of its own, augmented without it; set aside
                        // when the buffer overwrote it after the turn's metadata was read.
                        destinations(&mut outputs, &bytes, samples.clone()).into_par_iter().enumerate().for_each(|(offset, outputs)| {
                            let sample = samples.start + offset;
                            STACK.with(|frames| {
                                let mut frames = frames.borrow_mut();
                                {
                                    let buffer = self.buffer.read().expect("replay lock");
                                    if redraw && !buffer.still_holds(refs[sample]) {
                                        stale.lock().expect("stale list").push(sample);
                                        return;
                                    }
                                    copy(&buffer, refs[sample], last_frames[sample], &mut frames);
                                }
                                augment(&frames, key(sample), outputs);
                            });
                        });
                    }
                    // Rare: drawn again, with metadata and frames read under one lock.
                    for sample in stale.into_inner().expect("stale list") {
                        let mut frames = Vec::new();
                        {
                            let buffer = self.buffer.read().expect("replay lock");
                            refresh(&buffer, sample, refs, metadata, &mut rng);
                            gather(&buffer, &refs[sample..=sample], metadata, sample);
                            copy(&buffer, refs[sample], metadata.last_frames[sample], &mut frames);
                        }
                        let outputs = destinations(&mut outputs, &bytes, sample..sample + 1).pop().expect("one sample");
                        augment(&frames, key(sample), outputs);
                    }
                })
            })?;
        } else {
            // State vectors are a few hundred bytes and their augmentations a multiply: the whole
            // batch under one lock takes less than one image turn.
            let buffer = self.buffer.read().expect("replay lock");
            gather(&buffer, refs, metadata, 0);
            for ((view, draws), out) in self.views.iter().zip(&draws).zip(outputs) {
                let Plan::State(plan) = &view.plan else { unreachable!("one observation format for every view") };
                for (sample, dst) in out.chunks_exact_mut(view.bytes).enumerate() {
                    match view.of {
                        TransitionPart::Obs => buffer.copy_observation(refs[sample], false, dst),
                        TransitionPart::NextObs => buffer.copy_stack_ending(refs[sample], metadata.last_frames[sample], dst),
                    }
                }
                let values: Vec<f32> = out.chunks_exact(4).map(|bytes| f32::from_le_bytes(bytes.try_into().unwrap())).collect();
                let mut augmented = vec![0.0f32; values.len()];
                plan.apply_keyed(&values, &mut augmented, draws, keys)?;
                for (bytes, value) in out.chunks_exact_mut(4).zip(&augmented) {
                    bytes.copy_from_slice(&value.to_le_bytes());
                }
            }
        }
        Ok(())
    }
}

impl Producer {
    /// Gather and augment the sequences starting at `batch.refs` into the observation memory
    /// `allocate` gave the batch (`len * steps` rows per view). Each sequence draws its
    /// augmentation once (its index in the batch is its key) and holds it over its steps; padding
    /// steps are zeros. As in `fill`, each turn reads its sequences' metadata under one read lock
    /// and each sequence copies its stacks under a read lock of its own; a sequence whose first
    /// frame the buffer overwrote meanwhile is drawn again.
    fn fill_sequences(
        &self,
        pool: &rayon::ThreadPool,
        batch: &mut Batch,
        sequence: &Sequence,
        draw_seed: u64,
        keep_going: &(dyn Fn() -> bool + Sync),
    ) -> Result<()> {
        let (size, steps) = (batch.refs.len(), sequence.length);
        batch.len = size;
        batch.sequence_steps = Some(steps);
        batch.obs_float32 = self.views.first().is_some_and(|view| matches!(view.plan, Plan::State(_)));
        batch.has_discount = self.spec.returns.is_some();
        let discount = self.spec.returns.map(|returns| returns.discount);
        let draws: Vec<Draws> = self.views.iter().map(|view| Draws { seed: draw_seed, ..view.draws }).collect();
        // A sample is a whole sequence: its steps' rows in every view.
        let bytes: Vec<usize> = self.views.iter().map(|view| steps * view.bytes).collect();
        let lens: Vec<usize> = bytes.iter().map(|bytes| size * bytes).collect();
        let mut outputs: Vec<&mut [u8]> = match &mut batch.slot {
            Some(slot) => slot.regions_mut(&lens),
            None => batch.views.iter_mut().zip(&lens).map(|(view, &len)| &mut view.data[..len]).collect(),
        };
        let stack_bytes = {
            let buffer = self.buffer.read().expect("replay lock");
            let layout = buffer.layout();
            batch.metadata.resize_steps(size * steps, layout.action_bytes);
            layout.frame_stack * layout.frame_bytes
        };
        let mut rng = ChaCha8Rng::seed_from_u64(draw_seed ^ 0x5E_ED0F_D2A5);
        // A sequence the buffer overwrote since it was drawn is replaced by a fresh draw.
        let refresh = |buffer: &ReplayBuffer, refs: &mut [TransitionRef], sample: usize, rng: &mut ChaCha8Rng| {
            if !buffer.still_holds_sequence(refs[sample]) {
                if let Some(fresh) = buffer.draw_one_sequence(sequence, rng) {
                    refs[sample] = fresh;
                }
            }
        };
        // Real steps per sequence, known once its metadata is gathered.
        let mut real = vec![0usize; size];
        let (refs, metadata) = (&mut batch.refs, &mut batch.metadata);
        let images = self.views.iter().all(|view| matches!(view.plan, Plan::Image(_)));
        // Writes the augmented steps of one sequence, from its stacks, into its rows of each view.
        let augment = |frames: &[u8], sample: usize, real: usize, outputs: Vec<&mut [u8]>| {
            for ((view, draws), dst) in self.views.iter().zip(&draws).zip(outputs) {
                let (padding_from, rows) = (real * view.bytes, dst);
                match &view.plan {
                    Plan::Image(plan) => {
                        let params = plan.draw(draws, sample as u64);
                        for (step, out) in rows[..padding_from].chunks_exact_mut(view.bytes).enumerate() {
                            plan.apply_sample(&frames[step * stack_bytes..(step + 1) * stack_bytes], out, &params);
                        }
                    }
                    Plan::State(plan) => {
                        let values: Vec<f32> = frames[..real * stack_bytes]
                            .chunks_exact(4)
                            .map(|bytes| f32::from_le_bytes(bytes.try_into().expect("4 bytes")))
                            .collect();
                        let mut augmented = vec![0.0f32; values.len()];
                        let keys = vec![sample as u64; real];
                        plan.apply_keyed(&values, &mut augmented, draws, Some(&keys)).expect("sizes checked in Producer::new");
                        for (bytes, value) in rows[..padding_from].chunks_exact_mut(4).zip(&augmented) {
                            bytes.copy_from_slice(&value.to_le_bytes());
                        }
                    }
                }
                rows[padding_from..].fill(0);
            }
        };
        let work = |samples: Range<usize>| {
            {
                let buffer = self.buffer.read().expect("replay lock");
                for sample in samples.clone() {
                    refresh(&buffer, refs, sample, &mut rng);
                    real[sample] = buffer.gather_sequence_at(refs[sample], sequence, discount, metadata, sample * steps);
                }
            }
            let stale = std::sync::Mutex::new(Vec::new());
            {
                let (refs, real) = (&refs[..], &real[..]);
                let destinations = destinations(&mut outputs, &bytes, samples.clone());
                let each = |(offset, outputs): (usize, Vec<&mut [u8]>)| {
                    let sample = samples.start + offset;
                    STACK.with(|frames| {
                        let mut frames = frames.borrow_mut();
                        frames.resize(real[sample] * stack_bytes, 0);
                        {
                            let buffer = self.buffer.read().expect("replay lock");
                            if !buffer.still_holds_sequence(refs[sample]) {
                                stale.lock().expect("stale list").push(sample);
                                return;
                            }
                            buffer.copy_sequence(refs[sample], real[sample], &mut frames);
                        }
                        augment(&frames, sample, real[sample], outputs);
                    });
                };
                if images {
                    destinations.into_par_iter().enumerate().for_each(each);
                } else {
                    destinations.into_iter().enumerate().for_each(each);
                }
            }
            // Rare: drawn again, with metadata and frames read under one lock.
            for sample in stale.into_inner().expect("stale list") {
                let mut frames = Vec::new();
                {
                    let buffer = self.buffer.read().expect("replay lock");
                    refresh(&buffer, refs, sample, &mut rng);
                    real[sample] = buffer.gather_sequence_at(refs[sample], sequence, discount, metadata, sample * steps);
                    frames.resize(real[sample] * stack_bytes, 0);
                    buffer.copy_sequence(refs[sample], real[sample], &mut frames);
                }
                let outputs = destinations(&mut outputs, &bytes, sample..sample + 1).pop().expect("one sample");
                augment(&frames, sample, real[sample], outputs);
            }
        };
        pool.install(|| in_turns(size, keep_going, work))
    }
}

/// A prioritized stream's hold on its exponent's sum tree: released when the stream ends, however
/// it ends.
struct ExponentHeld {
    buffer: Arc<RwLock<ReplayBuffer>>,
    exponent: f64,
}

impl ExponentHeld {
    fn acquire(buffer: &Arc<RwLock<ReplayBuffer>>, exponent: f64) -> Result<Self> {
        buffer.write().expect("replay lock").acquire_priorities(exponent)?;
        Ok(Self { buffer: buffer.clone(), exponent })
    }
}

impl Drop for ExponentHeld {
    fn drop(&mut self) {
        if let Ok(mut buffer) = self.buffer.write() {
            buffer.release_priorities(self.exponent);
        }
    }
}
