//! The replay buffer and the producer against an independent model: every frame encodes (env,
//! episode, t), every transition the model saw is remembered with the stacks it must come back with.

use std::collections::HashMap;
use std::sync::{Arc, RwLock};

use radserve_augment::{FrameShape, Pipeline, Sharing, TransitionPart};
use radserve_replay::{
    BufferKind, ObservationFormat, Output, Prioritized, Producer, RecordedStep, ReplayBuffer, ReplayLayout, Returns, SampleSpec, SharedRing,
    Source, TransitionMetadata, TransitionRef, ViewSpec,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const SHAPE: FrameShape = FrameShape::new(3, 3, 4, 4); // k = 3 RGB 4x4 frames
const FRAME_BYTES: usize = 3 * 4 * 4;

fn frame(env: usize, episode: u32, t: u32) -> Vec<u8> {
    let mut bytes = vec![0u8; FRAME_BYTES];
    bytes[0] = env as u8;
    bytes[1] = episode as u8;
    bytes[2] = t as u8;
    bytes[3] = (t >> 8) as u8;
    for (index, byte) in bytes.iter_mut().enumerate().skip(4) {
        *byte = (index as u32 * 7 + t * 13 + episode * 29) as u8;
    }
    bytes
}

#[derive(Clone, Debug)]
struct Expected {
    obs: Vec<u8>,
    next_obs: Vec<u8>,
    action: Vec<u8>,
    reward: f32,
    terminated: bool,
    truncated: bool,
}

/// Drive `num_envs` envs for `steps` steps with random episode ends; returns the buffer and, keyed
/// by (env, step index), every transition with the stacks a correct buffer must rebuild.
fn simulate(num_envs: usize, capacity: usize, steps: u64, seed: u64) -> (ReplayBuffer, HashMap<(u32, u64), Expected>) {
    let layout = ReplayLayout { kind: BufferKind::Replay, capacity, num_envs, frame_stack: 3, frame_bytes: FRAME_BYTES, action_bytes: 2 };
    let mut buffer = ReplayBuffer::new(layout).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut episode = vec![0u32; num_envs];
    let mut t = vec![0u32; num_envs];
    // The session's stacking: the first frame fills the stack.
    let mut stacks: Vec<Vec<Vec<u8>>> = (0..num_envs).map(|env| vec![frame(env, 0, 0); 3]).collect();
    for env in 0..num_envs {
        buffer.record_first_frame(env, &frame(env, 0, 0), 0);
    }
    let mut expected = HashMap::new();
    for step in 0..steps {
        for env in 0..num_envs {
            let action = [rng.random::<u8>(), env as u8];
            let reward = rng.random_range(-1.0..1.0f64);
            let ends = rng.random_bool(0.08);
            let terminated = ends && rng.random_bool(0.5);
            let truncated = ends && !terminated;
            t[env] += 1;
            let next = frame(env, episode[env], t[env]);
            let obs = stacks[env].concat();
            stacks[env].remove(0);
            stacks[env].push(next.clone());
            let next_obs = stacks[env].concat();
            buffer.record_step(env, &RecordedStep { action: &action, reward, terminated, truncated, next_frame: &next, step_index: step, acted: None });
            expected.insert(
                (env as u32, step),
                Expected { obs, next_obs, action: action.to_vec(), reward: reward as f32, terminated, truncated },
            );
            if ends {
                episode[env] += 1;
                t[env] = 0;
                let first = frame(env, episode[env], 0);
                stacks[env] = vec![first.clone(); 3];
                buffer.record_first_frame(env, &first, step + 1);
            }
        }
    }
    (buffer, expected)
}

#[test]
fn sampled_transitions_are_the_ones_the_envs_produced() {
    for (num_envs, capacity, steps) in [(1, 40, 30), (1, 40, 500), (3, 60, 400), (4, 1000, 100)] {
        let (mut buffer, expected) = simulate(num_envs, capacity, steps, 7);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut refs = Vec::new();
        buffer.sample(2000, &mut rng, &mut refs).unwrap();
        let mut metadata = Default::default();
        buffer.gather_metadata(&refs, &mut metadata);
        let oldest_step = steps.saturating_sub((capacity / num_envs) as u64);
        let mut stack = vec![0u8; 3 * FRAME_BYTES];
        for (index, transition) in refs.iter().enumerate() {
            let key = (metadata.env_indices[index], metadata.step_indices[index]);
            let want = &expected[&key];
            buffer.copy_observation(*transition, false, &mut stack);
            assert_eq!(stack, want.obs, "obs of {key:?}");
            buffer.copy_observation(*transition, true, &mut stack);
            assert_eq!(stack, want.next_obs, "next_obs of {key:?}");
            assert_eq!(&metadata.actions[index * 2..index * 2 + 2], want.action.as_slice());
            assert_eq!(metadata.rewards[index], want.reward);
            assert_eq!(metadata.terminated[index] == 1, want.terminated);
            assert_eq!(metadata.truncated[index] == 1, want.truncated);
            // Only recent transitions survive: the ring holds about capacity / num_envs per env.
            assert!(key.1 + 3 >= oldest_step, "{key:?} should have been overwritten (oldest {oldest_step})");
        }
        let len = buffer.len();
        assert!(len <= capacity && len >= capacity.min(steps as usize * num_envs) * 8 / 10, "len {len} of {capacity}");
    }
}

#[test]
fn sampling_is_uniform_over_stored_transitions() {
    let (mut buffer, _) = simulate(2, 200, 2000, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut refs = Vec::new();
    let draws = 200_000;
    buffer.sample(draws, &mut rng, &mut refs).unwrap();
    let mut counts: HashMap<TransitionRef, usize> = HashMap::new();
    for transition in &refs {
        *counts.entry(*transition).or_default() += 1;
    }
    let stored = buffer.len();
    assert_eq!(counts.len(), stored, "every stored transition is drawn");
    let mean = draws as f64 / stored as f64;
    let worst = counts.values().map(|c| (*c as f64 - mean).abs()).fold(0.0, f64::max);
    assert!(worst < 6.0 * mean.sqrt(), "counts deviate by {worst} around {mean}");
    assert_eq!(buffer.counters().samples, draws as u64);
}

#[test]
fn memory_is_computed_up_front_and_frames_are_stored_about_once() {
    let layout = ReplayLayout { kind: BufferKind::Replay, capacity: 100_000, num_envs: 1, frame_stack: 3, frame_bytes: 3 * 100 * 100, action_bytes: 24 };
    assert!(layout.frames_per_transition() < 1.001);
    assert_eq!(layout.memory_bytes(), 100_003 * (30_000 + 24 + 33));
    let many = ReplayLayout { num_envs: 16, ..layout };
    assert!(many.frames_per_transition() < 1.001);
    // With episodes of 250 steps (cheetah at action repeat 4) one more frame per episode: 1.004.
    let (buffer, _) = simulate(2, 100, 10, 1);
    assert_eq!(buffer.layout().slots_per_env(), 53);
    assert!(ReplayLayout { capacity: 0, ..layout }.validate().is_err());
}

#[test]
fn an_empty_buffer_refuses_to_sample() {
    let layout = ReplayLayout { kind: BufferKind::Replay, capacity: 10, num_envs: 1, frame_stack: 3, frame_bytes: 4, action_bytes: 1 };
    let mut buffer = ReplayBuffer::new(layout).unwrap();
    let mut refs = Vec::new();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    assert!(buffer.sample(1, &mut rng, &mut refs).is_err());
    buffer.record_first_frame(0, &[1; 4], 0);
    assert!(buffer.sample(1, &mut rng, &mut refs).is_err(), "a first frame is not a transition");
    buffer.record_step(0, &RecordedStep { action: &[3], reward: 1.0, terminated: false, truncated: false, next_frame: &[2; 4], step_index: 0, acted: None });
    buffer.sample(5, &mut rng, &mut refs).unwrap();
    assert_eq!(refs.len(), 5);
}

/// Replay batches with next_obs, seed 11, prefetch 2 (views and returns: none).
fn replay_spec(batch_size: usize, text: &str, max_batches: Option<u64>) -> SampleSpec {
    SampleSpec {
        source: Source::Replay,
        include_next_obs: true,
        batch_size,
        pipeline: Pipeline::parse(text).unwrap(),
        sharing: Sharing::Reference,
        seed: 11,
        prefetch: 2,
        min_size: 1,
        samples_per_insert: None,
        error_buffer: 0.0,
        max_batches,
        views: Vec::new(),
        returns: None,
        prioritized: None,
        sequence: None,
    }
}

/// The bytes of view `name` of a heap batch.
fn view<'a>(batch: &'a radserve_replay::Batch, name: &str) -> &'a [u8] {
    &batch.view(name).unwrap_or_else(|| panic!("no view {name}")).data
}

fn producer(buffer: ReplayBuffer, text: &str, batch_size: usize) -> (Producer, Arc<RwLock<ReplayBuffer>>) {
    let shared = Arc::new(RwLock::new(buffer));
    let spec = replay_spec(batch_size, text, Some(3));
    (Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec).unwrap(), shared)
}

#[test]
fn the_producer_delivers_batches_in_order_with_real_stacks() {
    let (buffer, expected) = simulate(2, 100, 200, 5);
    let (producer, _) = producer(buffer, "none", 64);
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap());
    let (mut ready, recycle) = producer.start(pool, Output::Heap);
    let mut seen = 0;
    while let Some(batch) = ready.blocking_recv() {
        let mut batch = batch.unwrap();
        assert_eq!(batch.index, seen);
        assert_eq!(batch.views.iter().map(|view| (view.name.as_str(), view.shape.clone())).collect::<Vec<_>>(),
            [("obs", vec![9, 4, 4]), ("next_obs", vec![9, 4, 4])]);
        assert!(!batch.has_discount);
        for sample in 0..batch.len {
            let key = (batch.metadata.env_indices[sample], batch.metadata.step_indices[sample]);
            let stack = 3 * FRAME_BYTES;
            assert_eq!(view(&batch, "obs")[sample * stack..(sample + 1) * stack], expected[&key].obs);
            assert_eq!(view(&batch, "next_obs")[sample * stack..(sample + 1) * stack], expected[&key].next_obs);
        }
        seen += 1;
        // Buffers handed back are reused (filled with garbage first: every byte must be rewritten).
        for view in &mut batch.views {
            view.data.fill(0xEE);
            let _ = recycle.send(std::mem::take(&mut view.data));
        }
    }
    assert_eq!(seen, 3, "max_batches ends the stream");
}

#[test]
fn shared_output_writes_the_same_batches_into_slots_and_waits_for_free_ones() {
    let (buffer, _) = simulate(2, 100, 200, 5);
    let (heap_producer, shared) = producer(buffer, "crop(3)|flip(p=0.5)", 16);
    let spec = |max_batches| replay_spec(16, "crop(3)|flip(p=0.5)", max_batches);
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap());
    let (mut heap, _recycle) = heap_producer.start(pool.clone(), Output::Heap);
    let expected: Vec<_> = std::iter::from_fn(|| heap.blocking_recv()).map(Result::unwrap).collect();
    assert_eq!(expected.len(), 3);

    let shared_producer = Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec(Some(3))).unwrap();
    let ring = SharedRing::create(2, &shared_producer.region_bytes()).unwrap();
    let (mut ready, _) = shared_producer.start(pool.clone(), Output::Shared(ring.clone()));
    let first = ready.blocking_recv().unwrap().unwrap();
    let second = ready.blocking_recv().unwrap().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(100));
    assert!(ready.try_recv().is_err(), "both slots are held: the third batch must wait for one");
    // The learner's view: memory the producer no longer writes into for these batches.
    let peer = radserve_shm::MemFile::from_fd(ring.fd().try_clone_to_owned().unwrap()).unwrap();
    let peer = peer.as_slice();
    let len = view(&expected[0], "obs").len();
    let slot_bytes = |batch: &radserve_replay::Batch, next: bool| {
        let slot = batch.slot.as_ref().expect("shared batches carry their slot");
        let offset = slot.region_offset(usize::from(next));
        peer[offset..offset + len].to_vec()
    };
    for (batch, reference) in [(&first, &expected[0]), (&second, &expected[1])] {
        assert!(batch.views.iter().all(|view| view.data.is_empty()));
        assert_eq!(batch.metadata, reference.metadata);
        assert_eq!(slot_bytes(batch, false), view(reference, "obs"), "batch {}", batch.index);
        assert_eq!(slot_bytes(batch, true), view(reference, "next_obs"), "batch {}", batch.index);
    }
    let freed = first.slot.as_ref().unwrap().index();
    drop(first);
    let third = ready.blocking_recv().unwrap().unwrap();
    assert_eq!(third.slot.as_ref().unwrap().index(), freed, "the released slot is reused");
    assert_eq!(slot_bytes(&third, false), view(&expected[2], "obs"));
    assert!(ready.blocking_recv().is_none(), "max_batches ends the stream");

    // A client that leaves while the producer waits for a slot frees the producer.
    let waiting = Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec(None)).unwrap();
    let small_ring = SharedRing::create(1, &waiting.region_bytes()).unwrap();
    let (mut ready, _) = waiting.start(pool, Output::Shared(small_ring));
    let held = ready.blocking_recv().unwrap().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(50));
    assert_eq!(shared.read().unwrap().active_producers(), 1);
    drop(ready);
    let started = std::time::Instant::now();
    while shared.read().unwrap().active_producers() > 0 {
        assert!(started.elapsed() < std::time::Duration::from_secs(2), "the producer still waits for a slot");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    drop(held);
}

#[test]
fn the_producer_augments_and_checks_the_request_first() {
    let (buffer, _) = simulate(1, 50, 100, 6);
    let (producer, shared) = producer(buffer, "crop(3)|flip(p=0.5)", 8);
    assert_eq!(producer.view_shapes(), [("obs", &[9usize, 3, 3][..]), ("next_obs", &[9, 3, 3][..])]);
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap());
    let (mut ready, _recycle) = producer.start(pool, Output::Heap);
    let batch = ready.blocking_recv().unwrap().unwrap();
    assert_eq!(view(&batch, "obs").len(), 8 * 9 * 3 * 3);
    let spec = |batch_size, text: &str, prefetch| SampleSpec {
        source: Source::Replay,
        include_next_obs: true,
        batch_size,
        pipeline: Pipeline::parse(text).unwrap(),
        sharing: Sharing::Reference,
        seed: 0,
        prefetch,
        min_size: 0,
        samples_per_insert: None,
        error_buffer: 0.0,
        max_batches: None,
        views: Vec::new(),
        returns: None,
        prioritized: None,
        sequence: None,
    };
    let refuse = |spec: SampleSpec, format| Producer::new(shared.clone(), format, spec).err().unwrap().to_string();
    let image = ObservationFormat::Image(SHAPE);
    assert!(refuse(spec(0, "none", 1), image).contains("batch_size must be between 1 and the replay capacity (50), got 0"));
    assert!(refuse(spec(51, "none", 1), image).contains("got 51"));
    assert!(refuse(spec(8, "crop(5)", 1), image).contains("needs frames of at least 5x5"));
    assert!(refuse(spec(8, "none", 0), image).contains("prefetch must be between 1 and 64"));
    assert!(refuse(spec(8, "crop(3)", 1), ObservationFormat::State(17)).contains("applies to images, not state vectors"));
}

#[test]
fn the_rate_limiter_holds_sampling_to_its_ratio() {
    let (buffer, _) = simulate(1, 500, 100, 8);
    let inserts = buffer.counters().inserts;
    let shared = Arc::new(RwLock::new(buffer));
    let spec = SampleSpec {
        source: Source::Replay,
        include_next_obs: true,
        batch_size: 10,
        pipeline: Pipeline::identity(),
        sharing: Sharing::Reference,
        seed: 0,
        prefetch: 1,
        min_size: 1,
        samples_per_insert: Some(2.0),
        error_buffer: 10.0,
        max_batches: None,
        views: Vec::new(),
        returns: None,
        prioritized: None,
        sequence: None,
    };
    let producer = Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec).unwrap();
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap());
    let (mut ready, _recycle) = producer.start(pool, Output::Heap);
    // 2 samples per insert after the first (min_size 1, Reverb's offset) + 10 of slack:
    // floor((2 * (inserts - 1) + 10) / 10) batches, then it waits.
    let allowed = (2 * (inserts - 1) + 10) / 10;
    for _ in 0..allowed {
        ready.blocking_recv().unwrap().unwrap();
    }
    std::thread::sleep(std::time::Duration::from_millis(100));
    assert!(ready.try_recv().is_err(), "no batch beyond the ratio");
    assert_eq!(shared.read().unwrap().counters().samples, allowed * 10);
}

/// A rollout of `steps` steps of `num_envs` envs with random episode ends, recorded as sessions do.
fn rollout_buffer(steps: u64, num_envs: usize, extra_steps: u64) -> ReplayBuffer {
    let layout = ReplayLayout::rollout(steps as usize, num_envs, 3, FRAME_BYTES, 2);
    let mut buffer = ReplayBuffer::new(layout).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut t = vec![0u32; num_envs];
    let mut episode = vec![0u32; num_envs];
    for env in 0..num_envs {
        buffer.record_first_frame(env, &frame(env, 0, 0), 0);
    }
    for step in 0..steps + extra_steps {
        for env in 0..num_envs {
            let ends = rng.random_bool(0.3);
            t[env] += 1;
            let next = frame(env, episode[env], t[env]);
            let action = [step as u8, env as u8];
            buffer.record_step(env, &RecordedStep { action: &action, reward: 0.0, terminated: ends, truncated: false, next_frame: &next, step_index: step, acted: None });
            if ends {
                episode[env] += 1;
                t[env] = 0;
                buffer.record_first_frame(env, &frame(env, episode[env], 0), step + 1);
            }
        }
    }
    buffer
}

fn rollout_spec(batch_size: usize, epochs: usize, per_env_draws: bool, text: &str) -> SampleSpec {
    SampleSpec {
        source: Source::Rollout { epochs, per_env_draws },
        include_next_obs: false,
        batch_size,
        pipeline: Pipeline::parse(text).unwrap(),
        sharing: Sharing::Reference,
        seed: 4,
        prefetch: 2,
        min_size: 0,
        samples_per_insert: None,
        error_buffer: 0.0,
        max_batches: None,
        views: Vec::new(),
        returns: None,
        prioritized: None,
        sequence: None,
    }
}

#[test]
fn rollout_epochs_cover_every_step_of_every_env_exactly_once() {
    // Episodes end at 30% of steps, so the ring holds many first frames; and 7 steps were taken
    // after an older rollout's worth, which must not appear.
    let (steps, num_envs) = (16u64, 4);
    let shared = Arc::new(RwLock::new(rollout_buffer(steps, num_envs, 7)));
    let producer = Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), rollout_spec(12, 3, false, "none")).unwrap();
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap());
    let (mut ready, _recycle) = producer.start(pool, Output::Heap);
    let mut epochs: Vec<Vec<(u32, u32)>> = vec![Vec::new()];
    let mut batches = 0;
    while let Some(batch) = ready.blocking_recv() {
        let batch = batch.unwrap();
        assert!(batch.view("next_obs").is_none(), "rollouts leave next_obs out");
        let t = batch.rollout_t.as_ref().unwrap();
        #[allow(clippy::needless_range_loop)] // one index into several parallel arrays
        for sample in 0..batch.len {
            let (env, step) = (batch.metadata.env_indices[sample], batch.metadata.step_indices[sample]);
            assert_eq!(step, 7 + u64::from(t[sample]), "t counts from the oldest step of the last rollout");
            assert_eq!(batch.metadata.actions[sample * 2..sample * 2 + 2], [step as u8, env as u8]);
            let current = epochs.last_mut().unwrap();
            current.push((t[sample], env));
            if current.len() == (steps as usize) * num_envs {
                epochs.push(Vec::new());
            }
        }
        batches += 1;
    }
    epochs.pop();
    assert_eq!(epochs.len(), 3);
    assert_eq!(batches, 3 * (64usize).div_ceil(12));
    for epoch in &epochs {
        let mut sorted = epoch.clone();
        sorted.sort();
        let all: Vec<(u32, u32)> = (0..steps as u32).flat_map(|t| (0..num_envs as u32).map(move |e| (t, e))).collect();
        assert_eq!(sorted, all, "each (t, env) exactly once per epoch");
    }
    assert_ne!(epochs[0], epochs[1], "a fresh order each epoch");
}

#[test]
fn rollout_draws_can_be_held_per_environment() {
    let shared = Arc::new(RwLock::new(rollout_buffer(8, 3, 0)));
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap());
    for (per_env, held) in [(true, true), (false, false)] {
        let producer = Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), rollout_spec(24, 2, per_env, "crop(2)")).unwrap();
        let (mut ready, _recycle) = producer.start(pool.clone(), Output::Heap);
        // Crop offsets, recovered from the frames' first bytes: byte 0 (env) sits at (0, 0) only
        // when the crop starts at the top-left corner, so compare whole crops of equal frames.
        let mut offsets: HashMap<u32, std::collections::HashSet<Vec<u8>>> = HashMap::new();
        while let Some(batch) = ready.blocking_recv() {
            let batch = batch.unwrap();
            for sample in 0..batch.len {
                let plane = &view(&batch, "obs")[sample * 9 * 4..sample * 9 * 4 + 4];
                // The position of the env byte tells the offset: (0,0) keeps it, others do not.
                let signature = plane.iter().map(|&v| u8::from(v == batch.metadata.env_indices[sample] as u8)).collect();
                offsets.entry(batch.metadata.env_indices[sample]).or_default().insert(signature);
            }
        }
        let varied = offsets.values().any(|set| set.len() > 1);
        assert_eq!(!varied, held, "per_env_draws={per_env}: {offsets:?}");
    }
}

#[test]
fn rollout_requests_are_checked_against_the_buffer() {
    let rollout = Arc::new(RwLock::new(rollout_buffer(8, 2, 0)));
    let image = ObservationFormat::Image(SHAPE);
    let replay_spec = SampleSpec { source: Source::Replay, ..rollout_spec(4, 1, false, "none") };
    let message = Producer::new(rollout.clone(), image, replay_spec).err().unwrap().to_string();
    assert!(message.contains("keeps a rollout, not a replay buffer"), "{message}");
    let (replay, _) = simulate(1, 50, 20, 1);
    let message = Producer::new(Arc::new(RwLock::new(replay)), image, rollout_spec(4, 1, false, "none")).err().unwrap().to_string();
    assert!(message.contains("keeps a replay buffer, not a rollout"), "{message}");
    let short = Arc::new(RwLock::new(ReplayBuffer::new(ReplayLayout::rollout(8, 2, 3, FRAME_BYTES, 2)).unwrap()));
    let message = Producer::new(short, image, rollout_spec(4, 1, false, "none")).err().unwrap().to_string();
    assert!(message.contains("needs 8 steps of every env; only 0 were taken"), "{message}");
    let message = Producer::new(rollout, image, rollout_spec(4, 0, false, "none")).err().unwrap().to_string();
    assert!(message.contains("epochs must be at least 1"), "{message}");
}

#[test]
fn transitions_the_buffer_overwrote_are_noticed_and_drawn_again() {
    let (buffer, expected) = simulate(1, 40, 500, 9);
    assert!(!buffer.still_holds(TransitionRef { env: 0, frame: 1 }), "step 0 is long gone from a 40-slot ring");
    assert!(!buffer.still_holds(TransitionRef { env: 3, frame: 499 }), "no such env");
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut metadata = Default::default();
    for _ in 0..200 {
        let fresh = buffer.draw_one(&mut rng).expect("the buffer holds transitions");
        assert!(buffer.still_holds(fresh));
        buffer.gather_metadata(&[fresh], &mut metadata);
        let want = &expected[&(metadata.env_indices[0], metadata.step_indices[0])];
        let mut stack = vec![0u8; 3 * FRAME_BYTES];
        buffer.copy_observation(fresh, false, &mut stack);
        assert_eq!(stack, want.obs);
    }
    assert_eq!(buffer.counters().samples, 0, "draws that replace stale ones are not counted twice");
}

/// A session stepping a small buffer while a stream samples it: every sample's frames agree with its
/// metadata, although the buffer wraps many times while batches are made (the lock is released
/// between a batch's turns).
#[test]
fn samples_stay_consistent_while_the_buffer_is_written() {
    let layout = ReplayLayout { kind: BufferKind::Replay, capacity: 600, num_envs: 1, frame_stack: 3, frame_bytes: FRAME_BYTES, action_bytes: 2 };
    let mut buffer = ReplayBuffer::new(layout).unwrap();
    buffer.record_first_frame(0, &frame(0, 0, 0), 0);
    for step in 0..600u64 {
        let next = frame(0, 0, step as u32 + 1);
        buffer.record_step(0, &RecordedStep { action: &[step as u8, 0], reward: step as f64, terminated: false, truncated: false, next_frame: &next, step_index: step, acted: None });
    }
    let shared = Arc::new(RwLock::new(buffer));
    let spec = replay_spec(512, "none", Some(60));
    let producer = Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec).unwrap();
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap());
    let (mut ready, _recycle) = producer.start(pool, Output::Heap);
    let writer = {
        let shared = shared.clone();
        std::thread::spawn(move || {
            for step in 600..60_000u64 {
                let next = frame(0, 0, step as u32 + 1);
                let recorded = RecordedStep { action: &[step as u8, 0], reward: step as f64, terminated: false, truncated: false, next_frame: &next, step_index: step, acted: None };
                shared.write().unwrap().record_step(0, &recorded);
            }
        })
    };
    let t_of = |bytes: &[u8]| u32::from(bytes[2]) | (u32::from(bytes[3]) << 8);
    let mut batches = 0;
    while let Some(batch) = ready.blocking_recv() {
        let batch = batch.unwrap();
        for sample in 0..batch.len {
            let step = batch.metadata.step_indices[sample];
            assert_eq!(batch.metadata.rewards[sample], step as f32);
            let stack = &view(&batch, "obs")[sample * 3 * FRAME_BYTES..][..3 * FRAME_BYTES];
            let next = &view(&batch, "next_obs")[sample * 3 * FRAME_BYTES..][..3 * FRAME_BYTES];
            // Frame t is the observation after step t - 1; the first frame fills the stack.
            let want = |t: i64| (t.max(0) as u32) & 0xFFFF;
            for k in 0..3 {
                assert_eq!(t_of(&stack[k * FRAME_BYTES..]), want(step as i64 - 2 + k as i64), "obs of step {step}");
                assert_eq!(t_of(&next[k * FRAME_BYTES..]), want(step as i64 - 1 + k as i64), "next_obs of step {step}");
            }
        }
        batches += 1;
    }
    writer.join().unwrap();
    assert_eq!(batches, 60);
}

/// The model's n-step window of (env, step): up to `n` rewards of its episode summed with
/// `discount`, the bootstrap's factor, the flags and the next observation after the last summed
/// step; None while the episode is in progress and fewer than `n` steps from it were taken.
fn model_window(
    expected: &HashMap<(u32, u64), Expected>,
    key: (u32, u64),
    n: u64,
    discount: f64,
) -> Option<(f64, f64, bool, bool, Vec<u8>)> {
    let (mut reward, mut factor) = (0.0, 1.0);
    for k in 0..n {
        let step = expected.get(&(key.0, key.1 + k))?;
        reward += factor * f64::from(step.reward);
        factor *= discount;
        if step.terminated {
            return Some((reward, 0.0, true, false, step.next_obs.clone()));
        }
        if step.truncated || k + 1 == n {
            return Some((reward, factor, false, step.truncated, step.next_obs.clone()));
        }
    }
    unreachable!("n >= 1")
}

#[test]
fn n_step_windows_match_a_model_of_the_episodes() {
    // Episodes end by termination and truncation (8% of steps); small rings wrap many times.
    let (mut cut_short, mut terminated, mut truncated) = (0, 0, 0);
    for (num_envs, capacity, steps) in [(1, 40, 500), (3, 90, 400), (2, 1000, 120)] {
        for n in [1usize, 3, 5] {
            let (mut buffer, expected) = simulate(num_envs, capacity, steps, 21 + n as u64);
            let returns = Returns::new(n, 0.9).unwrap();
            let mut rng = ChaCha8Rng::seed_from_u64(3);
            let mut refs = Vec::new();
            buffer.sample_windows(3000, n, &mut rng, &mut refs).unwrap();
            let mut metadata = TransitionMetadata::default();
            buffer.gather_metadata(&refs, &mut metadata);
            buffer.gather_returns_at(&refs, returns, &mut metadata, 0);
            let mut stack = vec![0u8; 3 * FRAME_BYTES];
            for (index, transition) in refs.iter().enumerate() {
                let key = (metadata.env_indices[index], metadata.step_indices[index]);
                let (reward, discount, ends, cut, next_obs) = model_window(&expected, key, n as u64, 0.9)
                    .unwrap_or_else(|| panic!("{key:?} was sampled before its {n} steps were taken"));
                assert!((f64::from(metadata.rewards[index]) - reward).abs() < 1e-5, "reward of {key:?}");
                assert!((f64::from(metadata.discounts[index]) - discount).abs() < 1e-6, "discount of {key:?}");
                assert_eq!((metadata.terminated[index] == 1, metadata.truncated[index] == 1), (ends, cut), "flags of {key:?}");
                buffer.copy_stack_ending(*transition, metadata.last_frames[index], &mut stack);
                assert_eq!(stack, next_obs, "the observation after the window of {key:?}");
                buffer.copy_observation(*transition, false, &mut stack);
                assert_eq!(stack, expected[&key].obs, "obs of {key:?}");
                if n > 1 {
                    cut_short += usize::from(metadata.discounts[index] != 0.9f64.powi(n as i32) as f32);
                    terminated += usize::from(ends);
                    truncated += usize::from(cut);
                }
            }
            // The last n - 1 steps of each episode in progress wait for their windows.
            let in_progress: usize = (0..num_envs as u32)
                .map(|env| (1..n as u64).filter(|back| model_window(&expected, (env, steps - back), n as u64, 0.9).is_none()).count())
                .sum();
            assert_eq!(buffer.sampleable(n), buffer.len() - in_progress);
        }
    }
    assert!(cut_short > 0 && terminated > 0 && truncated > 0, "windows end early both ways: {cut_short} {terminated} {truncated}");
}

/// Views of a DrQ batch with a CURL pair and SVEA's shared draws: obs as stored, two crops drawn
/// independently, a crop and a crop-then-flip that share their draws, and next_obs three steps on.
fn drq_views() -> Vec<ViewSpec> {
    let view = |name: &str, of, text: &str, draws: Option<&str>| ViewSpec {
        name: name.into(),
        of,
        pipeline: Pipeline::parse(text).unwrap(),
        draws: draws.map(str::to_owned),
    };
    vec![
        view("obs", TransitionPart::Obs, "none", None),
        view("anchor", TransitionPart::Obs, "crop(3)", None),
        view("positive", TransitionPart::Obs, "crop(3)", None),
        view("svea_clean", TransitionPart::Obs, "crop(3)", Some("svea")),
        view("svea_strong", TransitionPart::Obs, "crop(3)|flip(p=1)", Some("svea")),
        view("next_obs", TransitionPart::NextObs, "none", None),
    ]
}

#[test]
fn named_views_carry_their_own_draws_and_the_n_step_next_obs() {
    let (buffer, expected) = simulate(2, 200, 300, 5);
    let shared = Arc::new(RwLock::new(buffer));
    let spec = SampleSpec { views: drq_views(), returns: Some(Returns::new(3, 0.99).unwrap()), ..replay_spec(64, "none", Some(2)) };
    let producer = Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec.clone()).unwrap();
    let sizes: Vec<usize> = [3 * 48, 81, 81, 81, 81, 3 * 48].iter().map(|bytes| 64 * bytes).collect();
    assert_eq!(producer.region_bytes(), sizes);
    assert_eq!(producer.stream_memory_bytes(), 4 * sizes.iter().sum::<usize>() as u64);
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap());
    let (mut ready, _recycle) = producer.start(pool.clone(), Output::Heap);
    let heap: Vec<_> = std::iter::from_fn(|| ready.blocking_recv()).map(Result::unwrap).collect();
    let mut independent = 0;
    for batch in &heap {
        assert!(batch.has_discount);
        let names: Vec<&str> = batch.views.iter().map(|view| view.name.as_str()).collect();
        assert_eq!(names, ["obs", "anchor", "positive", "svea_clean", "svea_strong", "next_obs"]);
        for sample in 0..batch.len {
            let key = (batch.metadata.env_indices[sample], batch.metadata.step_indices[sample]);
            let (_, discount, ..) = model_window(&expected, key, 3, 0.99).unwrap();
            let (_, _, _, _, next_obs) = model_window(&expected, key, 3, 0.99).unwrap();
            assert!((f64::from(batch.metadata.discounts[sample]) - discount).abs() < 1e-6);
            let at = |name: &str, bytes: usize| &view(batch, name)[sample * bytes..(sample + 1) * bytes];
            assert_eq!(at("obs", 3 * FRAME_BYTES), expected[&key].obs);
            assert_eq!(at("next_obs", 3 * FRAME_BYTES), next_obs);
            // The strong view is the clean one flipped: the same crop.
            let (clean, strong) = (at("svea_clean", 81), at("svea_strong", 81));
            for row in 0..9 * 3 {
                let mut flipped = clean[row * 3..row * 3 + 3].to_vec();
                flipped.reverse();
                assert_eq!(strong[row * 3..row * 3 + 3], flipped);
            }
            independent += usize::from(at("anchor", 81) != at("positive", 81));
        }
    }
    assert!(independent > 64, "anchor and positive are cropped independently ({independent} of 128 differ)");
    // Through shared memory: the same batches, one region per view.
    let shared_producer = Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec).unwrap();
    let ring = SharedRing::create(4, &shared_producer.region_bytes()).unwrap();
    let (mut ready, _) = shared_producer.start(pool, Output::Shared(ring.clone()));
    let peer = radserve_shm::MemFile::from_fd(ring.fd().try_clone_to_owned().unwrap()).unwrap();
    for reference in &heap {
        let batch = ready.blocking_recv().unwrap().unwrap();
        assert_eq!(batch.metadata, reference.metadata);
        let slot = batch.slot.as_ref().unwrap();
        for (region, view) in reference.views.iter().enumerate() {
            assert_eq!(&peer.as_slice()[slot.region_offset(region)..][..view.data.len()], view.data.as_slice(), "{}", view.name);
        }
    }
}

#[test]
fn views_and_returns_are_checked_before_any_batch() {
    let (buffer, _) = simulate(1, 50, 100, 6);
    let shared = Arc::new(RwLock::new(buffer));
    let image = ObservationFormat::Image(SHAPE);
    let with_views = |views: Vec<ViewSpec>| SampleSpec { views, ..replay_spec(8, "none", None) };
    let refuse = |spec: SampleSpec| Producer::new(shared.clone(), image, spec).err().unwrap().to_string();
    let obs = |name: &str, text: &str| ViewSpec::new(name, TransitionPart::Obs, Pipeline::parse(text).unwrap());
    assert!(refuse(with_views((0..9).map(|i| obs(&format!("v{i}"), "none")).collect())).contains("at most 8 views, got 9"));
    assert!(refuse(with_views(vec![obs("Obs", "none")])).contains("lowercase names"));
    assert!(refuse(with_views(vec![obs("", "none")])).contains("lowercase names"));
    assert!(refuse(with_views(vec![obs(&"x".repeat(33), "none")])).contains("lowercase names"));
    assert!(refuse(with_views(vec![obs("reward", "none")])).contains("is a field every batch has"));
    assert!(refuse(with_views(vec![obs("a", "none"), obs("a", "crop(3)")])).contains("named twice"));
    let message = refuse(with_views(vec![obs("a", "none"), obs("b", "crop(5)")]));
    assert!(message.starts_with("view \"b\": ") && message.contains("crop(5) needs frames of at least 5x5"), "{message}");
    // 8 views of 512 translated stacks: over the batch bound, naming the views.
    let big = (0..8).map(|i| obs(&format!("v{i}"), "translate(2000)")).collect();
    let message = Producer::new(shared.clone(), image, SampleSpec { views: big, ..replay_spec(50, "none", None) }).err().unwrap().to_string();
    assert!(message.contains("views v0, v1") && message.contains("the most allowed is"), "{message}");
    assert!(Returns::new(0, 0.9).unwrap_err().to_string().contains("n_step must be between 1 and 64, got 0"));
    assert!(Returns::new(65, 0.9).is_err());
    for discount in [-0.1, 1.1, f64::NAN] {
        assert!(Returns::new(3, discount).unwrap_err().to_string().contains("discount must be in [0, 1]"));
    }
    let rollout = Arc::new(RwLock::new(rollout_buffer(8, 2, 0)));
    let spec = SampleSpec { returns: Some(Returns::new(3, 0.9).unwrap()), ..rollout_spec(4, 1, false, "none") };
    let message = Producer::new(rollout, image, spec).err().unwrap().to_string();
    assert!(message.contains("n_step and discount apply to replay"), "{message}");
}

/// The batches of a stream of `spec` on `shared`, on heap buffers.
fn collect(shared: &Arc<RwLock<ReplayBuffer>>, spec: SampleSpec) -> Vec<radserve_replay::Batch> {
    let pool = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap());
    let producer = Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec).unwrap();
    let (mut ready, _recycle) = producer.start(pool, Output::Heap);
    std::iter::from_fn(|| ready.blocking_recv()).map(Result::unwrap).collect()
}

#[test]
fn a_prioritized_stream_reserves_its_priorities_and_tree() {
    let (buffer, _) = simulate(2, 200, 30, 5);
    let slots = buffer.layout().num_envs * buffer.layout().slots_per_env();
    let shared = Arc::new(RwLock::new(buffer));
    let memory = |prioritized| {
        let spec = SampleSpec { prioritized, ..replay_spec(64, "none", None) };
        Producer::new(shared.clone(), ObservationFormat::Image(SHAPE), spec).unwrap().stream_memory_bytes()
    };
    let uniform = memory(None);
    assert_eq!(uniform, 4 * 64 * 2 * 3 * FRAME_BYTES as u64);
    // 206 slots: 8 bytes each, and a tree of 256 leaves at 16 bytes.
    assert_eq!(slots, 206);
    assert_eq!(memory(Some(Prioritized::new(0.6, 0.4).unwrap())) - uniform, 206 * 8 + 256 * 16);
    assert_eq!(radserve_replay::priority_memory_bytes(slots), 206 * 8 + 256 * 16);
}

#[test]
fn a_prioritized_stream_draws_by_priority_with_keys_probabilities_and_weights() {
    let (buffer, expected) = simulate(2, 200, 300, 5);
    let shared = Arc::new(RwLock::new(buffer));
    let prioritized = |exponent, beta| Some(Prioritized::new(exponent, beta).unwrap());
    // The first prioritized stream gives every transition priority 1: uniform, weights 1.
    let first = collect(&shared, SampleSpec { prioritized: prioritized(1.0, 1.0), ..replay_spec(64, "none", Some(2)) });
    let held = shared.read().unwrap().len();
    for batch in &first {
        assert!(batch.prioritized && !batch.has_discount);
        assert_eq!(batch.table_size, held);
        let metadata = &batch.metadata;
        for sample in 0..batch.len {
            let transition = TransitionRef::from_key(metadata.keys[sample]);
            assert_eq!(transition.env as u32, metadata.env_indices[sample]);
            let key = (metadata.env_indices[sample], metadata.step_indices[sample]);
            let stack = 3 * FRAME_BYTES;
            assert_eq!(view(batch, "obs")[sample * stack..(sample + 1) * stack], expected[&key].obs, "{key:?}");
            assert!((metadata.probabilities[sample] - 1.0 / held as f64).abs() < 1e-15);
            assert_eq!(metadata.weights[sample], 1.0);
        }
    }
    // One transition at priority 99, the rest of the first batch at 0: alpha 1 draws it with
    // probability 99 / (99 + the transitions never updated).
    let keys = &first[0].metadata.keys;
    let mut distinct = keys.clone();
    distinct.sort_unstable();
    distinct.dedup();
    let priorities: Vec<f64> = keys.iter().map(|&key| if key == keys[0] { 99.0 } else { 0.0 }).collect();
    let update = shared.write().unwrap().update_priorities(keys, &priorities).unwrap();
    assert_eq!((update.updated, update.missing), (keys.len(), 0));
    let rest = (held - distinct.len()) as f64;
    let want = 99.0 / (99.0 + rest);
    let batches = collect(&shared, SampleSpec { prioritized: prioritized(1.0, 0.5), ..replay_spec(200, "none", Some(25)) });
    let (mut hits, mut draws) = (0usize, 0usize);
    for batch in &batches {
        let metadata = &batch.metadata;
        let largest = (0..batch.len).map(|i| (held as f64 * metadata.probabilities[i]).powf(-0.5)).fold(0.0, f64::max);
        for sample in 0..batch.len {
            let key = metadata.keys[sample];
            assert!(key == keys[0] || !distinct.contains(&key), "a transition at priority 0 was drawn");
            let probability = if key == keys[0] { want } else { 1.0 / (99.0 + rest) };
            assert!((metadata.probabilities[sample] - probability).abs() < 1e-12);
            let weight = (held as f64 * probability).powf(-0.5) / largest;
            assert!((f64::from(metadata.weights[sample]) - weight).abs() < 1e-6);
            hits += usize::from(key == keys[0]);
            draws += 1;
        }
    }
    let sd = (want * (1.0 - want) / draws as f64).sqrt();
    assert!((hits as f64 / draws as f64 - want).abs() < 5.0 * sd, "{hits} of {draws} draws, p {want}");
    // The largest priority set stays what new transitions enter at.
    assert_eq!(shared.read().unwrap().max_priority(), Some(99.0));
}

#[test]
fn prioritized_requests_are_checked_before_any_batch() {
    let shared = Arc::new(RwLock::new(rollout_buffer(4, 2, 0)));
    let spec = SampleSpec { prioritized: Some(Prioritized::new(0.6, 0.4).unwrap()), ..rollout_spec(4, 1, false, "none") };
    let message = Producer::new(shared, ObservationFormat::Image(SHAPE), spec).err().unwrap().to_string();
    assert!(message.contains("prioritized sampling applies to replay"), "{message}");
    for (alpha, beta, field) in [(-0.1, 0.4, "priority_exponent"), (0.6, 1.5, "importance_sampling_exponent"), (f64::NAN, 0.4, "priority_exponent")] {
        let message = Prioritized::new(alpha, beta).unwrap_err().to_string();
        assert!(message.contains(field) && message.contains("[0, 1]"), "{message}");
    }
}
