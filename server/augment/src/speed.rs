//! Timing of whole batches against a plain parallel copy of the same output bytes, for the
//! `radserve augment-bench` table (criterion benches in `benches/` cover the same cases).

use std::time::Instant;

use rayon::prelude::*;

use crate::draw::Draws;
use crate::error::Result;
use crate::plan::ImagePlan;
use crate::shape::FrameShape;
use crate::spec::Pipeline;

/// The paper's cases: crop/translate/window on 100x100 renders, the rest on 84x84 crops, and DrQ's
/// shift and intensity on 84x84 renders, three stacked RGB frames per sample (the criterion benches and `radserve augment-bench` time these).
pub const PAPER_CASES: [(&str, usize); 14] = [
    ("crop(84)", 100),
    ("translate(108)", 100),
    ("window(84)", 100),
    ("center_crop(84)", 100),
    ("flip(p=1)", 84),
    ("rotate(p=1)", 84),
    ("cutout", 84),
    ("cutout_color", 84),
    ("grayscale(p=1)", 84),
    ("conv", 84),
    ("color_jitter", 84),
    ("shift(4)", 84),
    ("intensity", 84),
    ("crop(84)|grayscale(p=0.3)", 100),
];

/// `len` pseudo-random bytes from a xorshift stream seeded by `seed`: every byte value appears and
/// neighbouring pixels differ, so benchmarks and tests see no shortcut a constant image would give.
pub fn noise(len: usize, seed: u64) -> Vec<u8> {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..len)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 24) as u8
        })
        .collect()
}

/// One measured pipeline.
#[derive(Clone, Debug)]
pub struct Measurement {
    pub pipeline: String,
    pub input: FrameShape,
    pub output: FrameShape,
    pub batch: usize,
    pub output_bytes: usize,
    /// Median seconds per batch.
    pub seconds: f64,
    /// Median seconds to copy `output_bytes` in parallel, measured interleaved with `seconds`.
    pub copy_seconds: f64,
}

impl Measurement {
    pub fn gigabytes_per_second(&self) -> f64 {
        self.output_bytes as f64 / self.seconds / 1e9
    }

    pub fn ratio_to_copy(&self) -> f64 {
        self.seconds / self.copy_seconds
    }
}

/// A copy of `source` into `target` split over the current rayon pool like the kernels are.
pub fn parallel_copy(source: &[u8], target: &mut [u8], pieces: usize) {
    let chunk = source.len().div_ceil(pieces.max(1)).max(1);
    target.par_chunks_mut(chunk).zip(source.par_chunks(chunk)).for_each(|(to, from)| to.copy_from_slice(from));
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Time `repeats` batches of `pipeline` on `input` (a whole batch of `shape` samples), alternating
/// with copies of the output bytes so both see the same machine state.
pub fn measure(pipeline: &Pipeline, shape: FrameShape, input: &[u8], repeats: usize) -> Result<Measurement> {
    let plan = ImagePlan::new(pipeline, shape)?;
    let batch = input.len() / shape.sample_len();
    let mut output = vec![0u8; batch * plan.output_shape().sample_len()];
    let copy_source = vec![1u8; output.len()];
    plan.apply(input, &mut output, &Draws::new(0))?; // warm-up: pages, scratch, threads
    parallel_copy(&copy_source, &mut output, batch);
    let (mut kernel_times, mut copy_times) = (Vec::new(), Vec::new());
    for repeat in 0..repeats.max(1) {
        let start = Instant::now();
        plan.apply(input, &mut output, &Draws::new(repeat as u64 + 1))?;
        kernel_times.push(start.elapsed().as_secs_f64());
        let start = Instant::now();
        parallel_copy(&copy_source, &mut output, batch);
        copy_times.push(start.elapsed().as_secs_f64());
    }
    Ok(Measurement {
        pipeline: pipeline.to_string(),
        input: shape,
        output: plan.output_shape(),
        batch,
        output_bytes: output.len(),
        seconds: median(kernel_times),
        copy_seconds: median(copy_times),
    })
}
