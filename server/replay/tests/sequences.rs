//! Sequences against an independent model of what the envs did: every frame the model saw is kept
//! with its stack and the step taken from it, and the model's own rule says where windows start.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, RwLock};

use radserve_augment::{FrameShape, Pipeline, Sharing, TransitionPart};
use radserve_replay::{
    Boundary, BufferKind, ObservationFormat, Output, Producer, RecordedStep, ReplayBuffer, ReplayLayout, Returns, SampleSpec, Sequence,
    Source, TransitionMetadata, TransitionRef, ViewSpec,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const STACK: usize = 3;
const FRAME_BYTES: usize = 3 * 4 * 4;
const SHAPE: FrameShape = FrameShape::new(STACK, 3, 4, 4);

fn frame(env: usize, episode: u32, t: u32) -> Vec<u8> {
    let mut bytes = vec![0u8; FRAME_BYTES];
    bytes[0] = env as u8 + 1;
    bytes[1] = episode as u8;
    bytes[2] = t as u8;
    for (index, byte) in bytes.iter_mut().enumerate().skip(3) {
        *byte = (index as u32 * 7 + t * 13 + episode * 29) as u8;
    }
    bytes
}

/// The step taken from a frame.
#[derive(Clone, Debug, PartialEq)]
struct Taken {
    action: Vec<u8>,
    reward: f32,
    terminated: bool,
    truncated: bool,
    step_index: u64,
}

/// What follows a frame: a step, its episode's end, or (the newest frame of a running episode)
/// nothing known yet.
#[derive(Clone, Debug, PartialEq)]
enum Next {
    Step(Taken),
    End,
    Unknown,
}

#[derive(Clone, Debug)]
struct ModelFrame {
    stack: Vec<u8>,
    first: bool,
    /// The frame an episode terminated with.
    terminal: bool,
    /// Steps since its episode's first frame.
    offset: u64,
    /// The step index that produced it (the reset's, for a first frame).
    produced_by: u64,
    next: Next,
}

/// Drives `num_envs` envs for `steps` steps: episodes end by termination, truncation, or a dead
/// worker (no flag; the next frame is a first frame), some shorter than a window.
fn simulate(num_envs: usize, capacity: usize, steps: u64, seed: u64) -> (ReplayBuffer, Vec<Vec<ModelFrame>>) {
    let layout =
        ReplayLayout { kind: BufferKind::Replay, capacity, num_envs, frame_stack: STACK, frame_bytes: FRAME_BYTES, action_bytes: 2 };
    let mut buffer = ReplayBuffer::new(layout).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut model: Vec<Vec<ModelFrame>> = vec![Vec::new(); num_envs];
    let mut episode = vec![0u32; num_envs];
    let mut stacks: Vec<Vec<Vec<u8>>> = vec![Vec::new(); num_envs];
    let start_episode = |env: usize, episode: u32, step: u64, buffer: &mut ReplayBuffer, stacks: &mut Vec<Vec<Vec<u8>>>, model: &mut Vec<Vec<ModelFrame>>| {
        let first = frame(env, episode, 0);
        stacks[env] = vec![first.clone(); STACK];
        buffer.record_first_frame(env, &first, step);
        model[env].push(ModelFrame { stack: stacks[env].concat(), first: true, terminal: false, offset: 0, produced_by: step, next: Next::Unknown });
    };
    for env in 0..num_envs {
        start_episode(env, 0, 0, &mut buffer, &mut stacks, &mut model);
    }
    for step in 0..steps {
        for env in 0..num_envs {
            let action = [rng.random::<u8>(), env as u8];
            let reward = rng.random_range(-1.0..1.0f64);
            let ends = rng.random_bool(0.06);
            let terminated = ends && rng.random_bool(0.5);
            let truncated = ends && !terminated;
            let offset = model[env].last().unwrap().offset + 1;
            let next = frame(env, episode[env], offset as u32);
            stacks[env].remove(0);
            stacks[env].push(next.clone());
            buffer.record_step(env, &RecordedStep { action: &action, reward, terminated, truncated, next_frame: &next, step_index: step, acted: None });
            let taken = Taken { action: action.to_vec(), reward: reward as f32, terminated, truncated, step_index: step };
            model[env].last_mut().unwrap().next = Next::Step(taken);
            model[env].push(ModelFrame { stack: stacks[env].concat(), first: false, terminal: terminated, offset, produced_by: step, next: Next::Unknown });
            let dies = !ends && rng.random_bool(0.01);
            if ends || dies {
                model[env].last_mut().unwrap().next = Next::End;
                if dies {
                    buffer.abandon_episode(env);
                }
                episode[env] += 1;
                start_episode(env, episode[env], step + 1, &mut buffer, &mut stacks, &mut model);
            }
        }
    }
    (buffer, model)
}

/// The first frame whose stack the ring still holds (the ring keeps capacity / envs + stack).
fn oldest_held(capacity: usize, num_envs: usize, written: usize) -> usize {
    let slots = capacity.div_ceil(num_envs) + STACK;
    (written + STACK).saturating_sub(slots + 1)
}

/// The model's rule for where a window may start.
fn model_starts(frames: &[ModelFrame], start: usize, sequence: &Sequence) -> bool {
    match sequence.boundary {
        Boundary::AcrossEpisodes => {
            let last = start + sequence.length - 1;
            start.is_multiple_of(sequence.period) && last < frames.len() && frames[last].next != Next::Unknown
        }
        Boundary::WithinEpisode => {
            if !frames[start].offset.is_multiple_of(sequence.period as u64) {
                return false;
            }
            for step in 0..sequence.length {
                match &frames[start + step].next {
                    Next::Step(_) => {}
                    Next::End => return step > sequence.burn_in,
                    Next::Unknown => return false,
                }
            }
            true
        }
    }
}

/// Checks rows `row..row + length` of `metadata` and their stacks against the model's frames.
fn check_rows(frames: &[ModelFrame], start: usize, sequence: &Sequence, metadata: &TransitionMetadata, row: usize, stacks: &[u8]) {
    let mut ended = false;
    for step in 0..sequence.length {
        let index = row + step;
        let at = format!("step {step} of the sequence at frame {start}");
        let stack = &stacks[step * STACK * FRAME_BYTES..(step + 1) * STACK * FRAME_BYTES];
        if ended {
            assert_eq!(metadata.mask[index], 0, "{at}: padding");
            assert!(stack.iter().all(|&byte| byte == 0), "{at}: a padding observation is zeros");
            assert_eq!((metadata.rewards[index], metadata.is_first[index], metadata.is_last[index]), (0.0, 0, 0), "{at}");
            continue;
        }
        let model = &frames[start + step];
        assert_eq!(metadata.mask[index], 1, "{at}");
        assert_eq!(stack, model.stack.as_slice(), "{at}: observation");
        assert_eq!(metadata.is_first[index] == 1, model.first, "{at}: is_first");
        assert_eq!(metadata.is_terminal[index] == 1, model.terminal, "{at}: is_terminal");
        match &model.next {
            Next::Step(taken) => {
                assert_eq!(metadata.is_last[index], 0, "{at}: is_last");
                assert_eq!(&metadata.actions[index * 2..index * 2 + 2], taken.action.as_slice(), "{at}: action");
                assert_eq!(metadata.rewards[index], taken.reward, "{at}: reward");
                assert_eq!((metadata.terminated[index] == 1, metadata.truncated[index] == 1), (taken.terminated, taken.truncated), "{at}");
                assert_eq!(metadata.step_indices[index], taken.step_index, "{at}: step index");
                let discount = if taken.terminated { 0.0 } else { 0.9 };
                assert_eq!(metadata.discounts[index], discount, "{at}: discount");
            }
            Next::End => {
                assert_eq!(metadata.is_last[index], 1, "{at}: is_last");
                assert_eq!(&metadata.actions[index * 2..index * 2 + 2], &[0, 0], "{at}: no action from a last frame");
                assert_eq!((metadata.rewards[index], metadata.discounts[index]), (0.0, 0.0), "{at}");
                assert_eq!(metadata.step_indices[index], model.produced_by, "{at}: step index");
                ended = sequence.boundary == Boundary::WithinEpisode;
            }
            Next::Unknown => panic!("{at}: drawn before its steps were recorded"),
        }
    }
}

#[test]
fn sequences_are_the_windows_the_envs_produced_and_every_one_is_drawn() {
    let mut seen = (0, 0, 0, 0); // padded, crossing an episode end, abandoned, terminal
    let cases = [
        (1, 120, 400, Sequence::new(8, 2, 1, Boundary::WithinEpisode).unwrap()),
        (3, 300, 300, Sequence::new(10, 3, 4, Boundary::WithinEpisode).unwrap()),
        (2, 200, 500, Sequence::new(6, 0, 1, Boundary::AcrossEpisodes).unwrap()),
        (2, 2000, 150, Sequence::new(12, 0, 3, Boundary::AcrossEpisodes).unwrap()),
        (4, 400, 200, Sequence::new(6, 0, 1, Boundary::WithinEpisode).unwrap()),
    ];
    for (case, (num_envs, capacity, steps, sequence)) in cases.into_iter().enumerate() {
        let (mut buffer, model) = simulate(num_envs, capacity, steps, 40 + case as u64);
        let mut rng = ChaCha8Rng::seed_from_u64(case as u64);
        let mut starts = Vec::new();
        let draws = 20_000;
        let samples_before = buffer.counters().samples;
        assert!(buffer.sample_sequences(draws, &sequence, &mut rng, &mut starts).unwrap());
        assert_eq!(buffer.counters().samples - samples_before, (draws * sequence.length) as u64, "steps count as samples");
        let mut metadata = TransitionMetadata::default();
        let rows = draws * sequence.length;
        metadata.actions.resize(rows * 2, 0);
        for column in [&mut metadata.is_first, &mut metadata.is_last, &mut metadata.is_terminal, &mut metadata.mask, &mut metadata.terminated, &mut metadata.truncated] {
            column.resize(rows, 0);
        }
        for column in [&mut metadata.rewards, &mut metadata.log_probs, &mut metadata.values, &mut metadata.discounts] {
            column.resize(rows, 0.0);
        }
        metadata.env_indices.resize(rows, 0);
        metadata.step_indices.resize(rows, 0);
        metadata.policy_versions.resize(rows, 0);
        metadata.keys.resize(rows, 0);
        metadata.last_frames.resize(rows, 0);
        let mut counts: HashMap<TransitionRef, usize> = HashMap::new();
        let mut stacks = vec![0u8; sequence.length * STACK * FRAME_BYTES];
        for (index, start) in starts.iter().enumerate() {
            *counts.entry(*start).or_default() += 1;
            let real = buffer.gather_sequence_at(*start, &sequence, Some(0.9), &mut metadata, index * sequence.length);
            stacks.fill(0);
            buffer.copy_sequence(*start, real, &mut stacks);
            let frames = &model[start.env];
            check_rows(frames, start.frame as usize, &sequence, &metadata, index * sequence.length, &stacks);
            let rows = index * sequence.length..(index + 1) * sequence.length;
            seen.0 += usize::from(metadata.mask[rows.clone()].contains(&0));
            seen.1 += usize::from(metadata.is_first[rows.start + 1..rows.end].contains(&1));
            seen.2 += usize::from(rows.clone().any(|row| metadata.is_last[row] == 1 && metadata.is_terminal[row] == 0 && metadata.truncated[row.saturating_sub(1)] == 0));
            seen.3 += usize::from(metadata.is_terminal[rows].contains(&1));
        }
        // Every start the model allows among the held frames is drawn, and nothing else, about
        // equally often.
        let allowed: HashSet<TransitionRef> = (0..num_envs)
            .flat_map(|env| {
                let frames = &model[env];
                (oldest_held(capacity, num_envs, frames.len())..frames.len())
                    .filter(|&start| model_starts(frames, start, &sequence))
                    .map(move |start| TransitionRef { env, frame: start as u64 })
            })
            .collect();
        let drawn: HashSet<TransitionRef> = counts.keys().copied().collect();
        assert_eq!(drawn, allowed, "case {case}: the starts drawn are the starts allowed");
        for start in &allowed {
            assert!(buffer.sequence_starts_at(start.env, start.frame, &sequence));
        }
        let mean = draws as f64 / allowed.len() as f64;
        let worst = counts.values().map(|&count| (count as f64 - mean).abs()).fold(0.0, f64::max);
        assert!(worst < 6.0 * mean.sqrt() + 1.0, "case {case}: counts deviate by {worst} around {mean}");
    }
    assert!(seen.0 > 0 && seen.1 > 0 && seen.2 > 0 && seen.3 > 0, "padding, crossings, abandoned and terminal episodes: {seen:?}");
}

#[test]
fn a_buffer_with_no_window_yet_draws_nothing() {
    let layout = ReplayLayout { kind: BufferKind::Replay, capacity: 100, num_envs: 1, frame_stack: 1, frame_bytes: 4, action_bytes: 1 };
    let mut buffer = ReplayBuffer::new(layout).unwrap();
    let sequence = Sequence::new(5, 0, 1, Boundary::AcrossEpisodes).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut starts = Vec::new();
    assert!(!buffer.sample_sequences(4, &sequence, &mut rng, &mut starts).unwrap());
    buffer.record_first_frame(0, &[1; 4], 0);
    for step in 0..4 {
        let record = RecordedStep { action: &[3], reward: 1.0, terminated: false, truncated: false, next_frame: &[2; 4], step_index: step, acted: None };
        buffer.record_step(0, &record);
        assert!(!buffer.sample_sequences(4, &sequence, &mut rng, &mut starts).unwrap(), "{} frames: no window yet", step + 2);
    }
    assert_eq!(buffer.counters().samples, 0, "nothing counted");
    let record = RecordedStep { action: &[3], reward: 1.0, terminated: false, truncated: false, next_frame: &[2; 4], step_index: 4, acted: None };
    buffer.record_step(0, &record);
    assert!(buffer.sample_sequences(4, &sequence, &mut rng, &mut starts).unwrap());
    assert!(starts.iter().all(|start| start.frame == 0), "the one window: frames 0..5, the step from frame 4 recorded");
}

#[test]
fn bounds_are_checked_before_anything_starts() {
    let error = |result: radserve_replay::Result<Sequence>| result.unwrap_err().to_string();
    assert!(error(Sequence::new(0, 0, 1, Boundary::WithinEpisode)).contains("between 1 and 1024"));
    assert!(error(Sequence::new(1025, 0, 1, Boundary::WithinEpisode)).contains("between 1 and 1024"));
    assert!(error(Sequence::new(80, 80, 1, Boundary::WithinEpisode)).contains("burn_in (80) must be below its length (80)"));
    assert!(error(Sequence::new(80, 40, 0, Boundary::WithinEpisode)).contains("period must be between 1"));
    let (buffer, _) = simulate(2, 100, 50, 1);
    let shared = Arc::new(RwLock::new(buffer));
    let spec = |sequence: Sequence| SampleSpec { sequence: Some(sequence), include_next_obs: false, ..spec(4) };
    let refused = |spec: SampleSpec| Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec).err().expect("refused").to_string();
    let within = Sequence::new(8, 2, 1, Boundary::WithinEpisode).unwrap();
    assert!(refused(spec(Sequence::new(50, 0, 1, Boundary::WithinEpisode).unwrap())).contains("needs 51 frames of one env"));
    assert!(refused(SampleSpec { include_next_obs: true, ..spec(within) }).contains("next observation is its next step"));
    let next_view = vec![ViewSpec::new("next_obs", TransitionPart::NextObs, Pipeline::identity())];
    assert!(refused(SampleSpec { views: next_view, ..spec(within) }).contains("views of obs only"));
    assert!(refused(SampleSpec { returns: Some(Returns::new(3, 0.9).unwrap()), ..spec(within) }).contains("n_step returns apply"));
    let prioritized = Some(radserve_replay::Prioritized::new(0.6, 0.4).unwrap());
    assert!(refused(SampleSpec { prioritized, ..spec(within) }).contains("sequences are drawn uniformly"));
    // 1 GiB at most per batch: 4096 sequences of 1024 steps of 144-byte stacks is 604 MB; of 9x
    // 84x84 stacks far more.
    let big = Sequence::new(1024, 0, 1, Boundary::WithinEpisode).unwrap();
    let big_layout = ReplayLayout { kind: BufferKind::Replay, capacity: 4096, num_envs: 1, frame_stack: 3, frame_bytes: 84 * 84 * 3, action_bytes: 1 };
    let big_buffer = Arc::new(RwLock::new(ReplayBuffer::new(big_layout).unwrap()));
    let message = Producer::new(big_buffer, ObservationFormat::Image(FrameShape::new(3, 3, 84, 84)), SampleSpec { batch_size: 64, ..spec(big) })
        .err()
        .unwrap()
        .to_string();
    assert!(message.contains("64 sequences of 1024 steps"), "{message}");
}

fn spec(batch_size: usize) -> SampleSpec {
    SampleSpec {
        source: Source::Replay,
        batch_size,
        include_next_obs: false,
        pipeline: Pipeline::identity(),
        sharing: Sharing::Reference,
        views: Vec::new(),
        returns: None,
        prioritized: None,
        sequence: None,
        seed: 5,
        prefetch: 2,
        min_size: batch_size,
        samples_per_insert: None,
        error_buffer: 0.0,
        max_batches: Some(3),
    }
}

/// A stream of sequences through the producer, both outputs: each sequence's augmentation is drawn
/// once and held over its steps (a flip is all or nothing), padding is zeros, the metadata is the
/// model's.
#[test]
fn a_producer_holds_each_sequences_draws_over_its_steps() {
    let (buffer, model) = simulate(2, 400, 300, 9);
    let shared = Arc::new(RwLock::new(buffer));
    let sequence = Sequence::new(10, 2, 1, Boundary::WithinEpisode).unwrap();
    let views = vec![
        ViewSpec::new("obs", TransitionPart::Obs, Pipeline::identity()),
        ViewSpec::new("flipped", TransitionPart::Obs, Pipeline::parse("flip(p=0.5)").unwrap()),
    ];
    let spec = SampleSpec { sequence: Some(sequence), views, returns: Some(Returns::new(1, 0.9).unwrap()), ..spec(32) };
    let stack_bytes = STACK * FRAME_BYTES;
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap());
    for shared_output in [false, true] {
        let producer = Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec.clone()).unwrap();
        assert_eq!(producer.region_bytes(), vec![32 * 10 * stack_bytes; 2]);
        let ring = shared_output.then(|| radserve_replay::SharedRing::create(4, &producer.region_bytes()).unwrap());
        let output = ring.clone().map_or(Output::Heap, Output::Shared);
        let (mut ready, _recycle) = producer.start(pool.clone(), output);
        let (mut flipped, mut kept) = (0, 0);
        for _ in 0..3 {
            let mut batch = ready.blocking_recv().unwrap().unwrap();
            assert_eq!((batch.len, batch.sequence_steps, batch.metadata.len), (32, Some(10), 320));
            let regions: Vec<Vec<u8>> = match batch.slot.take() {
                Some(mut slot) => slot.regions_mut(&[320 * stack_bytes; 2]).into_iter().map(|region| region.to_vec()).collect(),
                None => batch.views.iter().map(|view| view.data.clone()).collect(),
            };
            for sample in 0..32 {
                let rows = sample * 10..(sample + 1) * 10;
                let obs = &regions[0][rows.start * stack_bytes..rows.end * stack_bytes];
                let env = batch.metadata.env_indices[rows.start] as usize;
                let start = (batch.metadata.last_frames[rows.start]) as usize;
                check_rows(&model[env], start, &sequence, &batch.metadata, rows.start, obs);
                let real = batch.metadata.mask[rows.clone()].iter().filter(|&&mask| mask == 1).count();
                let flip = |stack: &[u8]| -> Vec<u8> {
                    stack.chunks_exact(4).flat_map(|row| row.iter().rev().copied().collect::<Vec<_>>()).collect()
                };
                let view = &regions[1][rows.start * stack_bytes..rows.end * stack_bytes];
                let steps: Vec<bool> = (0..real)
                    .map(|step| {
                        let (stack, out) = (&obs[step * stack_bytes..][..stack_bytes], &view[step * stack_bytes..][..stack_bytes]);
                        assert!(out == stack || out == flip(stack).as_slice(), "a flip or not");
                        out != stack
                    })
                    .collect();
                assert!(steps.iter().all(|&step| step == steps[0]), "one draw for the whole sequence: {steps:?}");
                if steps[0] {
                    flipped += 1;
                } else {
                    kept += 1;
                }
                assert!(view[real * stack_bytes..10 * stack_bytes].iter().all(|&byte| byte == 0), "padding is zeros");
            }
        }
        assert!(flipped > 10 && kept > 10, "draws differ between sequences: {flipped} {kept}");
    }
}
