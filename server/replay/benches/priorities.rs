//! Prioritized sampling against uniform sampling on the same buffer of 1M transitions (8 envs,
//! stacks of 3 one-byte frames: the draws, not the copies), the sum tree alone (a batch of 256 draws
//! and 256 priority updates), sequence draws (32 windows of 80 steps: R2D2's within episodes,
//! Dreamer's across them), and what recording one step of an 84x84x3 frame costs the replay (the
//! insert path under a session's steps). `cargo bench -p radserve-replay --bench priorities`;
//! compare the rows of one run (these machines are noisy).

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};
use radserve_replay::{Boundary, BufferKind, RecordedStep, ReplayBuffer, ReplayLayout, Sequence, SumTree};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const TRANSITIONS: usize = 1 << 20;
const ENVS: usize = 8;
const BATCH: usize = 256;

/// A full buffer of TRANSITIONS with episodes of 1000 steps.
fn full_buffer() -> ReplayBuffer {
    let layout =
        ReplayLayout { kind: BufferKind::Replay, capacity: TRANSITIONS, num_envs: ENVS, frame_stack: 3, frame_bytes: 1, action_bytes: 1 };
    let mut buffer = ReplayBuffer::new(layout).unwrap();
    for env in 0..ENVS {
        buffer.record_first_frame(env, &[0], 0);
    }
    for step in 0..(TRANSITIONS / ENVS + 16) as u64 {
        for env in 0..ENVS {
            let ends = step % 1000 == 999;
            let recorded = RecordedStep {
                action: &[1],
                reward: 1.0,
                terminated: false,
                truncated: ends,
                next_frame: &[2],
                step_index: step,
                acted: None,
            };
            buffer.record_step(env, &recorded);
            if ends {
                buffer.record_first_frame(env, &[0], step + 1);
            }
        }
    }
    buffer
}

fn sampling(c: &mut Criterion) {
    let mut buffer = full_buffer();
    buffer.acquire_priorities(0.6).unwrap();
    // Priorities spread over four orders of magnitude, as TD errors are.
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let (mut refs, mut probabilities) = (Vec::new(), Vec::new());
    buffer.sample(TRANSITIONS, &mut rng, &mut refs).unwrap();
    let keys: Vec<u64> = refs.iter().map(|transition| transition.key()).collect();
    for chunk in keys.chunks(1 << 16) {
        let values: Vec<f64> = chunk.iter().map(|_| 10f64.powf(rng.random_range(-3.0..1.0))).collect();
        buffer.update_priorities(chunk, &values).unwrap();
    }
    let mut group = c.benchmark_group("1M transitions, batch 256");
    group.bench_function("uniform sample", |b| b.iter(|| buffer.sample(BATCH, &mut rng, &mut refs).unwrap()));
    group.bench_function("prioritized sample", |b| {
        b.iter(|| buffer.sample_prioritized(BATCH, 1, 0.6, &mut rng, &mut refs, &mut probabilities).unwrap())
    });
    group.bench_function("prioritized sample, 3-step", |b| {
        b.iter(|| buffer.sample_prioritized(BATCH, 3, 0.6, &mut rng, &mut refs, &mut probabilities).unwrap())
    });
    group.bench_function("update 256 priorities", |b| {
        b.iter_batched(
            || {
                let start = rng.random_range(0..keys.len() - BATCH);
                let values: Vec<f64> = (0..BATCH).map(|_| rng.random::<f64>()).collect();
                (keys[start..start + BATCH].to_vec(), values)
            },
            |(batch_keys, values)| buffer.update_priorities(&batch_keys, &values).unwrap(),
            BatchSize::SmallInput,
        )
    });
    group.finish();

    let mut tree = SumTree::from_leaves((0..TRANSITIONS).map(|_| rng.random::<f64>()));
    let mut group = c.benchmark_group("sum tree of 1M leaves");
    group.bench_function("256 draws", |b| b.iter(|| (0..BATCH).map(|_| tree.draw(&mut rng).unwrap()).sum::<usize>()));
    group.bench_function("256 sets", |b| {
        b.iter(|| {
            for _ in 0..BATCH {
                let leaf = rng.random_range(0..TRANSITIONS);
                tree.set(leaf, rng.random::<f64>());
            }
        })
    });
    group.finish();

    let mut group = c.benchmark_group("1M transitions, 32 sequences of 80");
    let r2d2 = Sequence::new(80, 40, 40, Boundary::WithinEpisode).unwrap();
    let dreamer = Sequence::new(80, 0, 1, Boundary::AcrossEpisodes).unwrap();
    group.bench_function("within episodes, period 40", |b| b.iter(|| buffer.sample_sequences(32, &r2d2, &mut rng, &mut refs).unwrap()));
    group.bench_function("across episodes, period 1", |b| b.iter(|| buffer.sample_sequences(32, &dreamer, &mut rng, &mut refs).unwrap()));
    group.finish();
}

/// One step of an 84x84x3 frame recorded into a full replay of 50k transitions (8 envs).
fn recording(c: &mut Criterion) {
    let frame_bytes = 84 * 84 * 3;
    let layout = ReplayLayout { kind: BufferKind::Replay, capacity: 50_000, num_envs: ENVS, frame_stack: 3, frame_bytes, action_bytes: 24 };
    let mut buffer = ReplayBuffer::new(layout).unwrap();
    let frame = vec![7u8; frame_bytes];
    let action = [0u8; 24];
    for env in 0..ENVS {
        buffer.record_first_frame(env, &frame, 0);
    }
    let mut step = 0u64;
    let mut record = |buffer: &mut ReplayBuffer| {
        let recorded = RecordedStep { action: &action, reward: 1.0, terminated: false, truncated: false, next_frame: &frame, step_index: step, acted: None };
        buffer.record_step((step % ENVS as u64) as usize, &recorded);
        step += 1;
    };
    for _ in 0..60_000 {
        record(&mut buffer);
    }
    let mut group = c.benchmark_group("50k transitions of 84x84x3 frames");
    group.bench_function("record one step", |b| b.iter(|| record(&mut buffer)));
    group.finish();
}

criterion_group!(benches, sampling, recording);
criterion_main!(benches);
