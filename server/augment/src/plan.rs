//! Pipelines checked against an observation shape, ready to run on batches.

use std::cell::RefCell;

use rayon::prelude::*;

use crate::draw::{self, standard_normal, Draws, StageParams};
use crate::error::{AugmentError, Result};
use crate::kernels::{run_stage, FloatScratch, Isa};
use crate::shape::FrameShape;
use crate::spec::{Augmentation, Domain, Pipeline};

/// The largest augmented sample (or intermediate) a plan may produce: 64 MiB, far above any
/// observation (a stack of three 108x108 RGB frames is 105 KB) and far below what would exhaust a
/// server's memory at a few hundred samples a batch.
pub const MAX_SAMPLE_BYTES: usize = 64 << 20;

/// The shape one stage turns `input` into, or why it cannot apply.
fn stage_output(augmentation: &Augmentation, input: &FrameShape) -> Result<FrameShape> {
    let name = augmentation.name();
    let does_not_fit =
        |message: String| Err(AugmentError::DoesNotFit { augmentation: name, observation: input.to_string(), message });
    let (height, width) = (input.height, input.width);
    if augmentation.domain() == Domain::State {
        return does_not_fit(format!("{augmentation} applies to state vectors, not images"));
    }
    if augmentation.needs_rgb() && input.channels != 3 {
        return does_not_fit(format!("{augmentation} needs RGB frames (3 channels per frame), got {}", input.channels));
    }
    match *augmentation {
        Augmentation::Crop { size } | Augmentation::CenterCrop { size } | Augmentation::Window { size } => {
            if size > height || size > width {
                return does_not_fit(format!(
                    "{augmentation} needs frames of at least {size}x{size}, got {height}x{width}"
                ));
            }
            if matches!(augmentation, Augmentation::Window { .. }) {
                return Ok(*input);
            }
            Ok(input.with_size(size, size))
        }
        Augmentation::Translate { size } | Augmentation::CenterTranslate { size } => {
            if size < height || size < width {
                return does_not_fit(format!(
                    "{augmentation} places the frame in a {size}x{size} canvas, which must be at least the frame's \
                     {height}x{width}; use crop to shrink"
                ));
            }
            Ok(input.with_size(size, size))
        }
        Augmentation::Shift { pad } => {
            if pad >= height || pad >= width {
                return does_not_fit(format!(
                    "{augmentation}: a shift of up to {pad} pixels must be less than the {height}x{width} frame's sides"
                ));
            }
            Ok(*input)
        }
        Augmentation::Rotate { .. } => {
            if height != width {
                return does_not_fit(format!("{augmentation} needs square frames, got {height}x{width}"));
            }
            Ok(*input)
        }
        Augmentation::Cutout { max, .. } | Augmentation::CutoutColor { max, .. } => {
            if max > height || max > width {
                return does_not_fit(format!(
                    "{augmentation}: a side of up to {max} pixels must fit in the {height}x{width} frame"
                ));
            }
            Ok(*input)
        }
        Augmentation::Grayscale { .. }
        | Augmentation::Flip { .. }
        | Augmentation::RandomConv
        | Augmentation::ColorJitter { .. }
        | Augmentation::Intensity { .. } => Ok(*input),
        Augmentation::AmplitudeScale { .. } | Augmentation::GaussianNoise { .. } => unreachable!("checked above"),
    }
}

fn check_buffers(batch_input: usize, batch_output: usize, sample_input: usize, sample_output: usize) -> Result<usize> {
    let buffer = |message: String| Err(AugmentError::Buffer { message });
    if sample_input == 0 {
        return buffer("the observation has no elements".into());
    }
    if !batch_input.is_multiple_of(sample_input) {
        return buffer(format!("input of {batch_input} elements is not a whole number of {sample_input}-element samples"));
    }
    let batch = batch_input / sample_input;
    if batch_output != batch * sample_output {
        return buffer(format!(
            "output holds {batch_output} elements; {batch} samples of {sample_output} need {}",
            batch * sample_output
        ));
    }
    Ok(batch)
}

fn check_keys(keys: Option<&[u64]>, batch: usize) -> Result<()> {
    match keys {
        Some(keys) if keys.len() != batch => {
            Err(AugmentError::Buffer { message: format!("{} draw keys for {batch} samples", keys.len()) })
        }
        _ => Ok(()),
    }
}

/// Per-thread buffers for pipelines of several stages and for the float kernels; they grow to the
/// largest sample seen and are then reused, so steady-state batches allocate nothing large.
#[derive(Default)]
struct Scratch {
    current: Vec<u8>,
    next: Vec<u8>,
    floats: FloatScratch,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::default();
}

/// An image pipeline checked against a frame shape: it knows its output shape and runs batches
/// `[batch, frames * channels, height, width]` of uint8 in parallel over the samples, on the
/// current rayon pool (run it inside `ThreadPool::install` to choose the threads).
#[derive(Clone, Debug)]
pub struct ImagePlan {
    stages: Vec<Augmentation>,
    /// `shapes[0]` is the input; `shapes[j + 1]` is what stage `j` produces.
    shapes: Vec<FrameShape>,
    isa: Isa,
}

impl ImagePlan {
    pub fn new(pipeline: &Pipeline, input: FrameShape) -> Result<Self> {
        if input.sample_len() == 0 {
            return Err(AugmentError::DoesNotFit {
                augmentation: "pipeline",
                observation: input.to_string(),
                message: "the observation has an empty dimension".into(),
            });
        }
        let mut shapes = vec![input];
        for augmentation in pipeline.stages() {
            let next = stage_output(augmentation, shapes.last().expect("starts with the input"))?;
            if next.sample_len() > MAX_SAMPLE_BYTES {
                return Err(AugmentError::DoesNotFit {
                    augmentation: augmentation.name(),
                    observation: input.to_string(),
                    message: format!(
                        "{augmentation} would make samples of {} bytes; the most allowed is {MAX_SAMPLE_BYTES}",
                        next.sample_len()
                    ),
                });
            }
            shapes.push(next);
        }
        Ok(Self { stages: pipeline.stages().to_vec(), shapes, isa: Isa::detect() })
    }

    /// Run the kernels with this instruction set instead of the best detected one.
    pub fn with_isa(mut self, isa: Isa) -> Self {
        self.isa = isa;
        self
    }

    pub fn stages(&self) -> &[Augmentation] {
        &self.stages
    }

    /// The input shape followed by the shape after each stage.
    pub fn shapes(&self) -> &[FrameShape] {
        &self.shapes
    }

    pub fn input_shape(&self) -> FrameShape {
        self.shapes[0]
    }

    pub fn output_shape(&self) -> FrameShape {
        *self.shapes.last().expect("starts with the input")
    }

    /// The parameters every stage uses for the sample with draw key `key`.
    pub fn draw(&self, draws: &Draws, key: u64) -> Vec<StageParams> {
        self.stages
            .iter()
            .enumerate()
            .map(|(index, augmentation)| {
                let mut rng = draws.rng(index, augmentation, key);
                draw::draw(augmentation, &self.shapes[index], &mut rng)
            })
            .collect()
    }

    /// Augment a batch; sample `i` draws with key `i`.
    pub fn apply(&self, input: &[u8], output: &mut [u8], draws: &Draws) -> Result<()> {
        self.apply_keyed(input, output, draws, None)
    }

    /// Augment a batch, sample `i` drawing with `keys[i]` (hold keys fixed to hold parameters).
    pub fn apply_keyed(&self, input: &[u8], output: &mut [u8], draws: &Draws, keys: Option<&[u64]>) -> Result<()> {
        let (input_len, output_len) = (self.input_shape().sample_len(), self.output_shape().sample_len());
        let batch = check_buffers(input.len(), output.len(), input_len, output_len)?;
        check_keys(keys, batch)?;
        output.par_chunks_mut(output_len).zip(input.par_chunks(input_len)).enumerate().for_each(|(index, (dst, src))| {
            let key = keys.map_or(index as u64, |keys| keys[index]);
            let params = self.draw(draws, key);
            SCRATCH.with(|scratch| self.run_sample(src, dst, &params, &mut scratch.borrow_mut()));
        });
        Ok(())
    }

    /// Run the stages on one sample with the given parameters (single-threaded).
    pub fn apply_sample(&self, src: &[u8], dst: &mut [u8], params: &[StageParams]) {
        assert_eq!(params.len(), self.stages.len(), "one parameter set per stage");
        assert_eq!(src.len(), self.input_shape().sample_len());
        assert_eq!(dst.len(), self.output_shape().sample_len());
        SCRATCH.with(|scratch| self.run_sample(src, dst, params, &mut scratch.borrow_mut()));
    }

    fn run_sample(&self, src: &[u8], dst: &mut [u8], params: &[StageParams], scratch: &mut Scratch) {
        let last = self.stages.len().checked_sub(1);
        let Some(last) = last else {
            dst.copy_from_slice(src);
            return;
        };
        // Stages ping-pong between two per-thread buffers; the first reads `src`, the last writes `dst`.
        let mut current = std::mem::take(&mut scratch.current);
        let mut next = std::mem::take(&mut scratch.next);
        for (index, (augmentation, stage_params)) in self.stages.iter().zip(params).enumerate() {
            let (input, output) = (&self.shapes[index], &self.shapes[index + 1]);
            let source: &[u8] = if index == 0 { src } else { &current[..input.sample_len()] };
            if index == last {
                run_stage(augmentation, stage_params, input, output, source, dst, &mut scratch.floats, self.isa);
            } else {
                if next.len() < output.sample_len() {
                    next.resize(output.sample_len(), 0);
                }
                let target = &mut next[..output.sample_len()];
                run_stage(augmentation, stage_params, input, output, source, target, &mut scratch.floats, self.isa);
                std::mem::swap(&mut current, &mut next);
            }
        }
        scratch.current = current;
        scratch.next = next;
    }
}

/// A state pipeline checked against a vector dimension: runs `[batch, dim]` float32 batches.
#[derive(Clone, Debug)]
pub struct StatePlan {
    stages: Vec<Augmentation>,
    dim: usize,
}

impl StatePlan {
    pub fn new(pipeline: &Pipeline, dim: usize) -> Result<Self> {
        for augmentation in pipeline.stages() {
            if augmentation.domain() == Domain::Image {
                return Err(AugmentError::DoesNotFit {
                    augmentation: augmentation.name(),
                    observation: format!("state vectors of dimension {dim}"),
                    message: format!("{augmentation} applies to images, not state vectors"),
                });
            }
        }
        if dim == 0 {
            return Err(AugmentError::DoesNotFit {
                augmentation: "pipeline",
                observation: "state vectors of dimension 0".into(),
                message: "the observation has no elements".into(),
            });
        }
        Ok(Self { stages: pipeline.stages().to_vec(), dim })
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Augment a batch; sample `i` draws with key `i`.
    pub fn apply(&self, input: &[f32], output: &mut [f32], draws: &Draws) -> Result<()> {
        self.apply_keyed(input, output, draws, None)
    }

    /// Augment a batch, sample `i` drawing with `keys[i]`. State batches are small, so this runs
    /// on the calling thread.
    pub fn apply_keyed(&self, input: &[f32], output: &mut [f32], draws: &Draws, keys: Option<&[u64]>) -> Result<()> {
        let batch = check_buffers(input.len(), output.len(), self.dim, self.dim)?;
        check_keys(keys, batch)?;
        output.copy_from_slice(input);
        for (index, row) in output.chunks_exact_mut(self.dim).enumerate() {
            let key = keys.map_or(index as u64, |keys| keys[index]);
            for (stage_index, augmentation) in self.stages.iter().enumerate() {
                let mut rng = draws.rng(stage_index, augmentation, key);
                match *augmentation {
                    // RAD's state augmentations (appendix, "random amplitude scaling"): multiply by
                    // z ~ U[alpha, beta], one z per sample (RAS-S) or one per dimension (RAS-M).
                    Augmentation::AmplitudeScale { per_dimension: false, alpha, beta } => {
                        let factor = uniform(&mut rng, alpha, beta);
                        row.iter_mut().for_each(|value| *value *= factor);
                    }
                    Augmentation::AmplitudeScale { per_dimension: true, alpha, beta } => {
                        row.iter_mut().for_each(|value| *value *= uniform(&mut rng, alpha, beta));
                    }
                    Augmentation::GaussianNoise { std } => {
                        row.iter_mut().for_each(|value| *value += std * standard_normal(&mut rng));
                    }
                    Augmentation::Crop { .. }
                    | Augmentation::Translate { .. }
                    | Augmentation::Window { .. }
                    | Augmentation::Shift { .. }
                    | Augmentation::Intensity { .. }
                    | Augmentation::CenterCrop { .. }
                    | Augmentation::CenterTranslate { .. }
                    | Augmentation::Grayscale { .. }
                    | Augmentation::Cutout { .. }
                    | Augmentation::CutoutColor { .. }
                    | Augmentation::Flip { .. }
                    | Augmentation::Rotate { .. }
                    | Augmentation::RandomConv
                    | Augmentation::ColorJitter { .. } => unreachable!("image stages; StatePlan::new refuses them"),
                }
            }
        }
        Ok(())
    }
}

fn uniform(rng: &mut impl rand::Rng, low: f32, high: f32) -> f32 {
    low + (high - low) * rng.random::<f32>()
}
