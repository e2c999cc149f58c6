//! The sum tree, the buffer's priorities and prioritized draws against direct computations.

use super::*;
use crate::{BufferKind, RecordedStep, ReplayLayout};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// A buffer of `num_envs` envs with stacks of 3 one-byte frames, `steps` steps taken with
/// episodes ending (by termination or truncation) with probability `end`.
fn buffer(num_envs: usize, capacity: usize) -> ReplayBuffer {
    let layout = ReplayLayout { kind: BufferKind::Replay, capacity, num_envs, frame_stack: 3, frame_bytes: 1, action_bytes: 1 };
    let mut buffer = ReplayBuffer::new(layout).unwrap();
    for env in 0..num_envs {
        buffer.record_first_frame(env, &[0], 0);
    }
    buffer
}

fn drive(buffer: &mut ReplayBuffer, steps: u64, end: f64, rng: &mut ChaCha8Rng) {
    for _ in 0..steps {
        let step_index = buffer.steps_recorded();
        for env in 0..buffer.layout().num_envs {
            let ends = rng.random_bool(end);
            let terminated = ends && rng.random_bool(0.5);
            let step = RecordedStep {
                action: &[1],
                reward: rng.random::<f64>(),
                terminated,
                truncated: ends && !terminated,
                next_frame: &[2],
                step_index,
                acted: None,
            };
            buffer.record_step(env, &step);
            if ends {
                buffer.record_first_frame(env, &[0], step_index + 1);
            }
        }
    }
}

/// The slots of the transitions the buffer can sample now, each with its transition.
fn sampleable_slots(buffer: &ReplayBuffer) -> Vec<(usize, TransitionRef)> {
    let mut slots = Vec::new();
    for env in 0..buffer.layout().num_envs {
        for frame in buffer.oldest_sampleable(env)..buffer.written[env] {
            let slot = buffer.slot(env, frame);
            if buffer.flags[slot] & FIRST_OF_EPISODE == 0 {
                slots.push((slot, TransitionRef { env, frame }));
            }
        }
    }
    slots
}

#[test]
fn the_priorities_hold_exactly_the_sampleable_transitions() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    // Several envs, wrap-around many times over, episodes of ~10 steps, acquired late.
    let mut buffer = buffer(3, 60);
    drive(&mut buffer, 50, 0.1, &mut rng);
    buffer.acquire_priorities(1.0).unwrap();
    for round in 0..40 {
        drive(&mut buffer, rng.random_range(1..30), 0.1, &mut rng);
        let held = sampleable_slots(&buffer);
        let priorities = buffer.priorities.as_ref().unwrap();
        let with_priority: Vec<usize> = (0..buffer.flags.len()).filter(|&slot| priorities.get(slot).is_some()).collect();
        let mut expected: Vec<usize> = held.iter().map(|(slot, _)| *slot).collect();
        expected.sort_unstable();
        assert_eq!(with_priority, expected, "round {round}");
        for (slot, transition) in held {
            assert_eq!(buffer.transition_in(slot), transition);
            assert_eq!(TransitionRef::from_key(transition.key()), transition);
        }
        let tree = buffer.tree(1.0).unwrap();
        assert_eq!(buffer.len(), sampleable_slots(&buffer).len(), "len counts first frames as they come and go");
        assert_eq!(tree.total(), buffer.len() as f64, "every transition at the initial priority 1");
    }
}

#[test]
fn draws_follow_the_priorities_among_complete_windows() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut buffer = buffer(2, 400);
    drive(&mut buffer, 150, 0.05, &mut rng);
    buffer.acquire_priorities(0.5).unwrap();
    let held = sampleable_slots(&buffer);
    let keys: Vec<u64> = held.iter().map(|(_, transition)| transition.key()).collect();
    let values: Vec<f64> = (0..keys.len()).map(|index| (index % 7) as f64).collect();
    let report = buffer.update_priorities(&keys, &values).unwrap();
    assert_eq!(report, PriorityUpdate { updated: keys.len(), missing: 0 });
    // With 3-step returns the last two transitions of an episode in progress cannot be drawn.
    let n_step = 3;
    let incomplete: Vec<TransitionRef> = buffer.incomplete_windows(n_step).collect();
    let weight = |index: usize| values[index].sqrt();
    let mass: f64 = held.iter().enumerate().filter(|(_, (_, t))| !incomplete.contains(t)).map(|(index, _)| weight(index)).sum();
    let draws = 300_000;
    let (mut refs, mut probabilities) = (Vec::new(), Vec::new());
    let table_size = buffer.sample_prioritized(draws, n_step, 0.5, &mut rng, &mut refs, &mut probabilities).unwrap();
    assert_eq!(table_size, held.len() - incomplete.len(), "what could be drawn: the complete windows");
    let mut counts = vec![0usize; held.len()];
    let position: std::collections::HashMap<TransitionRef, usize> =
        held.iter().enumerate().map(|(index, (_, transition))| (*transition, index)).collect();
    for (transition, probability) in refs.iter().zip(&probabilities) {
        let index = position[transition];
        assert!(!incomplete.contains(transition), "{transition:?}'s window is incomplete");
        assert!((probability - weight(index) / mass).abs() < 1e-12, "the probability of {transition:?}");
        counts[index] += 1;
    }
    for (index, count) in counts.iter().enumerate() {
        let p = if incomplete.contains(&held[index].1) { 0.0 } else { weight(index) / mass };
        let sd = (p * (1.0 - p) / draws as f64).sqrt();
        assert!((*count as f64 / draws as f64 - p).abs() <= 5.0 * sd + 1e-9, "transition {index}: {count} draws, p {p}");
    }
    assert_eq!(counts[0], 0, "priority 0 under exponent 0.5 is never drawn");
    assert_eq!(buffer.counters().samples, draws as u64);
    // A replacement draw comes with its probability too.
    let (transition, probability) = buffer.draw_one_prioritized(n_step, 0.5, &mut rng).unwrap();
    assert!((probability - weight(position[&transition]) / mass).abs() < 1e-12);
}

#[test]
fn updates_are_checked_before_anything_changes() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut buffer = buffer(2, 40);
    drive(&mut buffer, 10, 0.0, &mut rng);
    let key = TransitionRef { env: 1, frame: 3 }.key();
    let error = buffer.update_priorities(&[key], &[2.0]).unwrap_err().to_string();
    assert!(error.contains("no prioritized stream sampled this replay"), "{error}");
    buffer.acquire_priorities(1.0).unwrap();
    let before = buffer.tree(1.0).unwrap().total();
    for (keys, values, expected) in [
        (vec![key, key], vec![1.0], "one entry each"),
        (vec![key, key], vec![3.0, f64::NAN], "priorities[1] is NaN"),
        (vec![key], vec![-0.5], "finite and non-negative"),
        (vec![key], vec![f64::INFINITY], "finite and non-negative"),
        (vec![key, TransitionRef { env: 2, frame: 1 }.key()], vec![3.0, 3.0], "keys[1]"),
    ] {
        let error = buffer.update_priorities(&keys, &values).unwrap_err().to_string();
        assert!(error.contains(expected), "{error}");
        assert_eq!(buffer.tree(1.0).unwrap().total(), before, "nothing changed");
    }
    let too_many = vec![key; MAX_PRIORITY_UPDATES + 1];
    assert!(buffer.update_priorities(&too_many, &vec![1.0; too_many.len()]).is_err());
    // Set, then a new transition enters at the largest priority set; an overwritten key is missing.
    assert_eq!(buffer.update_priorities(&[key], &[6.0]).unwrap(), PriorityUpdate { updated: 1, missing: 0 });
    assert_eq!(buffer.max_priority(), Some(6.0));
    drive(&mut buffer, 1, 0.0, &mut rng);
    let newest = TransitionRef { env: 0, frame: buffer.written[0] - 1 };
    assert_eq!(buffer.priority(newest), Some(6.0));
    drive(&mut buffer, 40, 0.0, &mut rng);
    assert_eq!(buffer.priority(TransitionRef::from_key(key)), None, "overwritten");
    assert_eq!(buffer.update_priorities(&[key], &[1.0]).unwrap(), PriorityUpdate { updated: 0, missing: 1 });
}

#[test]
fn importance_weights_scale_down_by_the_batch_largest() {
    let mut weights = Vec::new();
    importance_weights(&[0.1, 0.2, 0.4], 10, 1.0, &mut weights);
    assert_eq!(weights, vec![1.0, 0.5, 0.25]);
    importance_weights(&[0.1, 0.2, 0.4], 10, 0.0, &mut weights);
    assert_eq!(weights, vec![1.0, 1.0, 1.0]);
    importance_weights(&[0.25, 0.01], 4, 0.5, &mut weights);
    assert!((weights[0] - 0.2).abs() < 1e-7 && weights[1] == 1.0, "{weights:?}");
}

#[test]
fn find_maps_each_prefix_to_its_leaf() {
    let tree = SumTree::from_leaves([1.0, 0.0, 2.0, 3.0, 0.0].into_iter());
    assert_eq!(tree.total(), 6.0);
    for (prefix, leaf) in [(0.0, 0), (0.99, 0), (1.0, 2), (2.99, 2), (3.0, 3), (5.99, 3)] {
        assert_eq!(tree.find(prefix), Some(leaf), "prefix {prefix}");
    }
    // A prefix at or past the total (rounding) stays in the last positive leaf.
    assert_eq!(tree.find(6.0), Some(3));
    assert_eq!(tree.find(7.5), Some(3));
    assert_eq!(SumTree::new(3).find(0.0), None);
}

#[test]
fn set_keeps_every_sum_exact() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let len = 1000;
    let mut tree = SumTree::new(len);
    let mut leaves = vec![0.0; len];
    for _ in 0..20_000 {
        let leaf = rng.random_range(0..len);
        let value = if rng.random_bool(0.2) { 0.0 } else { rng.random::<f64>() * 10.0 };
        tree.set(leaf, value);
        leaves[leaf] = value;
    }
    let rebuilt = SumTree::from_leaves(leaves.iter().copied());
    assert_eq!(tree.nodes, rebuilt.nodes, "updates and a rebuild agree bit for bit");
    for (leaf, value) in leaves.iter().enumerate() {
        assert_eq!(tree.get(leaf), *value);
    }
}

#[test]
fn draws_follow_the_weights() {
    let weights = [0.5, 0.0, 3.0, 1.5, 5.0];
    let tree = SumTree::from_leaves(weights.into_iter());
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let draws = 200_000;
    let mut counts = [0usize; 5];
    for _ in 0..draws {
        counts[tree.draw(&mut rng).expect("positive total")] += 1;
    }
    assert_eq!(counts[1], 0, "a zero leaf is never drawn");
    for (leaf, &weight) in weights.iter().enumerate() {
        let p = weight / 10.0;
        let sd = (p * (1.0 - p) / draws as f64).sqrt();
        let observed = counts[leaf] as f64 / draws as f64;
        assert!((observed - p).abs() <= 5.0 * sd + 1e-12, "leaf {leaf}: {observed} vs {p}");
    }
}

#[test]
fn priorities_keep_one_tree_per_exponent_in_step() {
    let mut priorities = Priorities::new(8);
    for slot in [1, 2, 5] {
        priorities.insert(slot);
    }
    priorities.acquire(0.5).unwrap();
    priorities.update(2, 4.0);
    priorities.acquire(1.0).unwrap();
    priorities.acquire(1.0).unwrap();
    priorities.insert(6); // at the largest priority seen: 4
    priorities.remove(1);
    assert_eq!(priorities.get(1), None);
    assert_eq!(priorities.get(6), Some(4.0));
    let full = priorities.tree(1.0).unwrap();
    assert_eq!(full.total(), 4.0 + 1.0 + 4.0);
    let half = priorities.tree(0.5).unwrap();
    assert!((half.total() - (2.0 + 1.0 + 2.0)).abs() < 1e-12);
    priorities.release(1.0);
    assert_eq!(priorities.exponents(), vec![(0.5, 1), (1.0, 1)]);
    priorities.release(1.0);
    priorities.release(0.5);
    assert!(priorities.exponents().is_empty());
}

#[test]
fn exponent_zero_is_uniform_and_the_exponents_are_bounded() {
    let mut priorities = Priorities::new(4);
    priorities.insert(0);
    priorities.insert(3);
    priorities.acquire(0.0).unwrap();
    priorities.update(0, 0.0);
    priorities.update(3, 100.0);
    assert_eq!(priorities.tree(0.0).unwrap().total(), 2.0, "0^0 = 1: every transition held counts once");
    for exponent in [0.25, 0.5, 0.75] {
        priorities.acquire(exponent).unwrap();
    }
    let error = priorities.acquire(1.0).unwrap_err().to_string();
    assert!(error.contains("4 priority exponents"), "{error}");
    assert!(Prioritized::new(1.5, 0.4).is_err() && Prioritized::new(0.6, f64::NAN).is_err());
}
