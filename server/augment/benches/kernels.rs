//! Every kernel at the paper's batch (512 samples of 3 stacked RGB frames), next to a plain copy of
//! the same output bytes (the memory-speed floor the targets are stated against).
//! `cargo bench -p radserve-augment` (add `-- crop` to filter).

use std::time::Duration;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use radserve_augment::speed::{noise, PAPER_CASES};
use radserve_augment::{Draws, FrameShape, ImagePlan, Pipeline};

const BATCH: usize = 512;

fn kernels(c: &mut Criterion) {
    let mut group = c.benchmark_group("augment");
    group.sample_size(10).warm_up_time(Duration::from_secs(1)).measurement_time(Duration::from_secs(2));
    let mut copied = std::collections::HashSet::new();
    for (text, side) in PAPER_CASES {
        let plan = ImagePlan::new(&Pipeline::parse(text).unwrap(), FrameShape::new(3, 3, side, side)).unwrap();
        let input = noise(BATCH * plan.input_shape().sample_len(), 1);
        let mut output = vec![0u8; BATCH * plan.output_shape().sample_len()];
        group.throughput(Throughput::Bytes(output.len() as u64));
        let mut seed = 0;
        group.bench_function(BenchmarkId::new(text, format!("{side}px")), |b| {
            b.iter(|| {
                seed += 1;
                plan.apply(&input, &mut output, &Draws::new(seed)).unwrap()
            })
        });
        // The baseline: copying the output's bytes, in parallel like the kernels (once per size).
        if !copied.insert(output.len()) {
            continue;
        }
        let source = noise(output.len(), 2);
        group.bench_function(BenchmarkId::new("copy", format!("{}B", output.len())), |b| {
            b.iter(|| parallel_copy(&source, &mut output))
        });
    }
    group.finish();
}

fn parallel_copy(source: &[u8], target: &mut [u8]) {
    radserve_augment::speed::parallel_copy(source, target, BATCH);
}

criterion_group!(benches, kernels);
criterion_main!(benches);
