//! Timing of whole batches against a plain parallel copy of the same output bytes, for the
//! `radserve augment-bench` table (criterion benches in `benches/` cover the same cases).

use std::time::Instant;

use rayon::prelude::*;

use crate::draw::Draws;
use crate::error::Result;
use crate::plan::ImagePlan;
use crate::shape::FrameShape;
use crate::spec::Pipeline;

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
