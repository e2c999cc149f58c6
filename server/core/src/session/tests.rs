//! Sessions against the fake simulators: stacking across episode ends, same-step autoreset with
//! final observations, replay recording of both kinds of episode end, recovery of a lost group,
//! simulators that raise, masked resets, info dicts, and EnvPool's asynchronous mode. The same
//! behaviour is tested against the real simulators end to end (tests/test_gymnasium_contract.py,
//! tests/test_worker_faults.py, tests/test_replay.py); here every case is exact and needs no Python.
//! The manager's policy (limits, budget, ownership, idle sessions) is tested in
//! `manager/tests.rs`, the server-side actor in `actor/tests.rs`.

use rand::SeedableRng;
use radserve_replay::TransitionRef;

use crate::error::CoreError;
use crate::infos::InfoColumn;
use crate::fake::{self, FakeSimulators, FAKE_ENV, FRAME_BYTES};
use crate::manager::{BufferRequest, SessionExtras};
use crate::session::{ResetSpec, Session, SessionConfig, StepOutcome};
use crate::space::DType;
use crate::test_support::*;

/// An episode that ended: its final stack, return and length.
type Ended = (Vec<u8>, f64, u64);

/// What a session should show of one env, computed from the fake's rules alone.
#[derive(Clone, Debug)]
struct EnvModel {
    seed: u64,
    episode: u64,
    /// Frames of the current episode so far.
    frames: Vec<[u8; FRAME_BYTES]>,
    episode_return: f64,
}

impl EnvModel {
    fn new(seed: u64) -> EnvModel {
        EnvModel { seed, episode: 0, frames: vec![fake::frame(seed, 0, 0)], episode_return: 0.0 }
    }

    /// The last `k` frames, the episode's first repeated where there are fewer (stacking at reset).
    fn stack(frames: &[[u8; FRAME_BYTES]], k: usize) -> Vec<u8> {
        (0..k).flat_map(|i| frames[(frames.len() + i).saturating_sub(k)]).collect()
    }

    /// One step with `action`: (reward, terminated, truncated, the episode if it ended).
    fn step(&mut self, action: i64, k: usize) -> (f64, bool, bool, Option<Ended>) {
        let reward = action as f64 + 1.0;
        self.episode_return += reward;
        let t = self.frames.len() as u64;
        self.frames.push(fake::frame(self.seed, self.episode, t));
        if t < fake::episode_length(self.seed) {
            return (reward, false, false, None);
        }
        let ended = (Self::stack(&self.frames, k), self.episode_return, t);
        let terminated = fake::ends_terminated(self.episode);
        self.episode += 1;
        self.frames = vec![fake::frame(self.seed, self.episode, 0)];
        self.episode_return = 0.0;
        (reward, terminated, !terminated, Some(ended))
    }
}

#[tokio::test]
async fn stacks_and_same_step_autoreset_follow_the_episodes_of_each_env() {
    let (_, manager) = manager(2, limits());
    let (num_envs, k) = (3, 3);
    let id = create(&manager, num_envs, 10, k as i64, SessionExtras::default()).await;
    let mut models: Vec<EnvModel> = (0..num_envs).map(|env| EnvModel::new(10 + env as u64)).collect();
    let obs = reset(&manager, &id, None).await;
    let expected: Vec<u8> = models.iter().flat_map(|model| EnvModel::stack(&model.frames, k)).collect();
    assert_eq!(obs, expected, "at reset each stack is the first frame repeated");

    let mut kinds = (0, 0);
    for step_index in 0..25 {
        let values: Vec<i64> = (0..num_envs).map(|env| ((step_index + env) % 3) as i64).collect();
        let outcome = step(&manager, &id, &values).await.unwrap();
        let mut final_obs = Vec::new();
        let mut episodes = Vec::new();
        for (env, model) in models.iter_mut().enumerate() {
            let (reward, terminated, truncated, ended) = model.step(values[env], k);
            assert_eq!(
                (outcome.rewards[env], outcome.terminated[env], outcome.truncated[env]),
                (reward, terminated, truncated),
                "env {env} at step {step_index}"
            );
            if let Some((stack, episode_return, length)) = ended {
                final_obs.extend(stack);
                episodes.push((env, episode_return, length, terminated, truncated));
                kinds.0 += usize::from(terminated);
                kinds.1 += usize::from(truncated);
            }
        }
        let expected: Vec<u8> = models.iter().flat_map(|model| EnvModel::stack(&model.frames, k)).collect();
        assert_eq!(outcome.obs, expected, "observations after step {step_index}");
        assert_eq!(outcome.final_obs, final_obs, "final observations of step {step_index}");
        let reported: Vec<_> = outcome
            .episodes
            .iter()
            .map(|end| (end.env_index, end.episode_return, end.episode_length, end.terminated, end.truncated))
            .collect();
        assert_eq!(reported, episodes, "episodes ended in step {step_index}");
        assert!(outcome.episodes.iter().all(|end| end.error.is_none()));
    }
    assert!(kinds.0 > 0 && kinds.1 > 0, "both kinds of episode end were seen: {kinds:?}");
    let info = manager.describe(&local(), &id).await.unwrap();
    assert_eq!(info.total_env_steps, 25 * num_envs as u64);
}

#[tokio::test]
async fn replay_records_every_transition_with_both_kinds_of_episode_end() {
    let (_, manager) = manager(2, limits());
    let (num_envs, k) = (3, 2);
    let extras = SessionExtras { buffer: Some(BufferRequest::Replay { capacity: 1000 }), observation_view: None, name: None };
    let id = create(&manager, num_envs, 4, k as i64, extras).await;
    reset(&manager, &id, None).await;
    for step_index in 0..30 {
        step(&manager, &id, &[(step_index % 3) as i64; 3]).await.unwrap();
    }
    let session = manager.get(&local(), &id).unwrap();
    let session = session.lock().await;
    let replay = session.replay().unwrap().clone();
    let mut replay = replay.write().unwrap();
    assert_eq!(replay.len(), 30 * num_envs, "one transition per env and step");

    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut refs: Vec<TransitionRef> = Vec::new();
    replay.sample(600, &mut rng, &mut refs).unwrap();
    let mut metadata = radserve_replay::TransitionMetadata::default();
    replay.gather_metadata(&refs, &mut metadata);
    let (mut obs, mut next_obs) = (vec![0; k * FRAME_BYTES], vec![0; k * FRAME_BYTES]);
    let mut kinds = (0, 0);
    for (row, transition) in refs.iter().enumerate() {
        replay.copy_observation(*transition, false, &mut obs);
        replay.copy_observation(*transition, true, &mut next_obs);
        let env = metadata.env_indices[row] as usize;
        let seed = 4 + env as u64;
        // The next frame says where the transition is: episode e, step t >= 1 of it.
        let [next_seed, episode, t, mark] = next_obs[(k - 1) * FRAME_BYTES..].try_into().unwrap();
        assert_eq!((next_seed as u64, mark), (seed, fake::MARK), "row {row}");
        let (episode, t) = (episode as u64, t as u64);
        assert!(t >= 1, "an episode's first frame is never a transition's next frame");
        let frames: Vec<_> = (0..=t).map(|i| fake::frame(seed, episode, i)).collect();
        assert_eq!(next_obs, EnvModel::stack(&frames, k), "next_obs of row {row}");
        assert_eq!(obs, EnvModel::stack(&frames[..t as usize], k), "obs of row {row}: same episode, one step earlier");
        let ended = t == fake::episode_length(seed);
        let terminated = ended && fake::ends_terminated(episode);
        let truncated = ended && !fake::ends_terminated(episode);
        assert_eq!((metadata.terminated[row] != 0, metadata.truncated[row] != 0), (terminated, truncated), "row {row}");
        kinds.0 += usize::from(terminated);
        kinds.1 += usize::from(truncated);
    }
    assert!(kinds.0 > 0 && kinds.1 > 0, "both kinds of episode end are recorded: {kinds:?}");
}

#[tokio::test]
async fn a_lost_group_ends_its_episodes_and_restarts_from_its_seeds() {
    let (simulators, manager) = manager(2, limits());
    let extras = SessionExtras { buffer: Some(BufferRequest::Replay { capacity: 100 }), observation_view: None, name: None };
    let id = create(&manager, 4, 19, 2, extras).await;
    reset(&manager, &id, None).await;
    step(&manager, &id, &[0, 0, 0, 0]).await.unwrap();
    let before = step(&manager, &id, &[1, 1, 1, 1]).await.unwrap().obs;

    // Envs 2 and 3 are the second group's.
    simulators.lose_group_of(3);
    let outcome = step(&manager, &id, &[2, 2, 2, 2]).await.unwrap();
    let stack = 2 * FRAME_BYTES;
    let lost: Vec<_> = outcome.episodes.iter().map(|end| (end.env_index, end.truncated, end.episode_length)).collect();
    assert_eq!(lost, vec![(2, true, 3), (3, true, 3)], "the lost group's episodes end as truncated");
    assert!(outcome.episodes.iter().all(|end| end.error.as_deref() == Some("fake worker died")));
    assert_eq!(outcome.final_obs, before[2 * stack..], "their last observation is the one before the lost step");
    assert_eq!(outcome.obs[2 * stack..3 * stack], [fake::frame(21, 0, 0), fake::frame(21, 0, 0)].concat());
    assert_eq!(outcome.obs[3 * stack..], [fake::frame(22, 0, 0), fake::frame(22, 0, 0)].concat(), "restarted from the seed");
    assert!(!outcome.terminated[2] && outcome.truncated[2] && outcome.truncated[3]);
    assert_eq!(outcome.obs[..stack], [fake::frame(19, 0, 2), fake::frame(19, 0, 3)].concat(), "the other group went on");

    let next = step(&manager, &id, &[0, 0, 0, 0]).await.unwrap();
    assert_eq!(next.obs[3 * stack..], [fake::frame(22, 0, 0), fake::frame(22, 0, 1)].concat(), "the session steps on");
    assert_eq!(manager.describe(&local(), &id).await.unwrap().episodes_completed, 3, "two lost, env 0's ended at step 4");
}

#[tokio::test]
async fn a_simulator_that_raises_ends_only_that_episode() {
    let (simulators, manager) = manager(1, limits());
    let id = create(&manager, 2, 0, 1, SessionExtras::default()).await;
    reset(&manager, &id, None).await;
    step(&manager, &id, &[0, 0]).await.unwrap();
    simulators.raise_in(1);
    let outcome = step(&manager, &id, &[0, 0]).await.unwrap();
    assert_eq!(outcome.episodes.len(), 1);
    let end = &outcome.episodes[0];
    assert_eq!((end.env_index, end.truncated, end.terminated), (1, true, false));
    assert_eq!(end.error.as_deref(), Some("FakeError: the simulator raised"));
    assert_eq!(outcome.final_obs, fake::frame(1, 0, 1), "the last frame before the step that raised");
    assert_eq!(outcome.obs, [fake::frame(0, 0, 2), fake::frame(1, 1, 0)].concat());
}

#[tokio::test]
async fn a_failed_step_asks_for_a_reset_and_bad_actions_reach_no_simulator() {
    let (simulators, manager) = manager(2, limits());
    let id = create(&manager, 2, 0, 1, SessionExtras::default()).await;
    let before_reset = step(&manager, &id, &[0, 0]).await.unwrap_err();
    assert!(matches!(before_reset, CoreError::NotReset), "{before_reset}");
    reset(&manager, &id, None).await;

    let steps = simulators.steps();
    let out_of_range = step(&manager, &id, &[0, 3]).await.unwrap_err().to_string();
    assert!(out_of_range.contains("action 3 of env 1 is outside [0, 3)"), "{out_of_range}");
    let session = manager.get(&local(), &id).unwrap();
    let wrong_dtype = session.lock().await.step(DType::Float32, &[2], &[0; 8]).await.unwrap_err().to_string();
    assert!(wrong_dtype.contains("actions must be int64 of shape [2]"), "{wrong_dtype}");
    assert_eq!(simulators.steps(), steps, "refused actions are never sent");

    simulators.fail_next_step("nonsense from the simulator");
    let failed = step(&manager, &id, &[0, 0]).await.unwrap_err();
    assert!(matches!(&failed, CoreError::Simulator(message) if message.contains("nonsense")), "{failed}");
    assert!(matches!(step(&manager, &id, &[0, 0]).await.unwrap_err(), CoreError::NotReset));
    reset(&manager, &id, Some(5)).await;
    let outcome = step(&manager, &id, &[0, 0]).await.unwrap();
    assert_eq!(outcome.obs, [fake::frame(5, 0, 1), fake::frame(6, 0, 1)].concat(), "reseeded: env i gets 5 + i");
}

/// gymnasium's NEXT_STEP and reset_mask, as the core serves them: skipped envs do not move and
/// record nothing; a masked reset resets only the envs it marks, with per-env seeds if given.
#[tokio::test]
async fn skipped_envs_stay_put_and_masked_resets_reset_only_their_envs() {
    let (_, manager) = manager(2, limits());
    let extras = SessionExtras { buffer: Some(BufferRequest::Replay { capacity: 100 }), ..SessionExtras::default() };
    let id = create(&manager, 4, 10, 1, extras).await;
    let session = manager.get(&local(), &id).unwrap();
    let mut session = session.lock().await;
    let frame = |obs: &[u8], env: usize| obs[env * FRAME_BYTES..][..3].to_vec();
    let bad = session.reset_with(&ResetSpec { mask: Some(vec![true, false, false, false]), ..ResetSpec::default() }).await;
    assert!(matches!(bad, Err(CoreError::InvalidMask(_))), "a masked reset needs a session reset once");
    let obs = session.reset(None).await.unwrap();
    assert_eq!((0..4).map(|env| frame(&obs, env)).collect::<Vec<_>>(), [[10, 0, 0], [11, 0, 0], [12, 0, 0], [13, 0, 0]]);

    let skip = [false, true, false, false];
    let outcome = session.step_except(DType::Int64, &[4], &actions(&[1, 1, 1, 1]), Some(&skip)).await.unwrap();
    assert_eq!(frame(&outcome.obs, 1), [11, 0, 0], "a skipped env keeps its frame");
    assert_eq!(frame(&outcome.obs, 0), [10, 0, 1]);
    assert_eq!(outcome.rewards, [2.0, 0.0, 2.0, 2.0]);
    assert_eq!(session.total_env_steps(), 3);
    assert_eq!(session.replay().unwrap().read().unwrap().len(), 3, "nothing recorded for the skipped env");

    // Env 1 alone starts a new episode (unseeded: its stream goes on); the others keep their step.
    let spec = ResetSpec { mask: Some(vec![false, true, false, false]), ..ResetSpec::default() };
    let obs = session.reset_with(&spec).await.unwrap();
    assert_eq!((0..4).map(|env| frame(&obs, env)).collect::<Vec<_>>(), [[10, 0, 1], [11, 1, 0], [12, 0, 1], [13, 0, 1]]);
    // Per-env seeds, used where the mask is true.
    let spec = ResetSpec { env_seeds: Some(vec![100, 7, 7, 40]), mask: Some(vec![true, false, false, true]), ..ResetSpec::default() };
    let obs = session.reset_with(&spec).await.unwrap();
    assert_eq!((0..4).map(|env| frame(&obs, env)).collect::<Vec<_>>(), [[100, 0, 0], [11, 1, 0], [12, 0, 1], [40, 0, 0]]);
    let outcome = session.step(DType::Int64, &[4], &actions(&[0, 0, 0, 0])).await.unwrap();
    assert_eq!(frame(&outcome.obs, 2), [12, 0, 2]);

    for (spec, what) in [
        (ResetSpec { mask: Some(vec![true; 3]), ..ResetSpec::default() }, "short mask"),
        (ResetSpec { mask: Some(vec![false; 4]), ..ResetSpec::default() }, "empty mask"),
        (ResetSpec { seed: Some(1), env_seeds: Some(vec![1; 4]), ..ResetSpec::default() }, "two kinds of seed"),
        (ResetSpec { env_seeds: Some(vec![1; 5]), ..ResetSpec::default() }, "seeds for 5 envs"),
    ] {
        assert!(matches!(session.reset_with(&spec).await, Err(CoreError::InvalidMask(_))), "{what}");
    }
    let short = session.step_except(DType::Int64, &[4], &actions(&[0; 4]), Some(&[true])).await;
    assert!(matches!(short, Err(CoreError::InvalidMask(_))));
    drop(session);
    manager.shutdown().await;
}

#[tokio::test]
async fn the_envs_info_dicts_travel_as_one_column_per_key_over_the_groups() {
    let (_, manager) = manager(2, limits());
    // Seeds 10, 11, 12: episodes of 4, 5 and 3 steps, the envs in two groups.
    let id = create(&manager, 3, 10, 1, SessionExtras::default()).await;
    reset(&manager, &id, None).await;
    let session = manager.get(&local(), &id).unwrap();
    let at_reset = session.lock().await.reset_infos().clone();
    assert_eq!(at_reset.columns, vec![InfoColumn::python_ints(&["fake_episode"], vec![0, 1, 2], &[0, 0, 0])]);
    for t in 1..=3u64 {
        let outcome = step(&manager, &id, &[0, 0, 0]).await.unwrap();
        // The two groups' columns joined in env order.
        assert_eq!(outcome.step_infos.columns, vec![InfoColumn::python_ints(&["fake_t"], vec![0, 1, 2], &[t as i64; 3])]);
        // The resets the server made in the step that ended an episode.
        let ended: Vec<u32> = (0..3).filter(|&env| t == fake::episode_length(10 + env as u64)).collect();
        let expected: Vec<InfoColumn> =
            (!ended.is_empty()).then(|| InfoColumn::python_ints(&["fake_episode"], ended.clone(), &vec![1; ended.len()])).into_iter().collect();
        assert_eq!(outcome.reset_infos.columns, expected, "step {t}");
    }
    // A skipped env reports nothing; a masked reset reports only the envs it reset.
    let mut session = session.lock().await;
    let outcome = session.step_except(DType::Int64, &[3], &actions(&[0, 0, 0]), Some(&[false, true, false])).await.unwrap();
    assert_eq!(outcome.step_infos.columns[0].envs, vec![0, 2]);
    session.reset_with(&ResetSpec { mask: Some(vec![false, true, false]), ..ResetSpec::default() }).await.unwrap();
    assert_eq!(session.reset_infos().columns[0].envs, vec![1]);
}

/// The env models of an async session's envs, which come back in any order: each env's first result
/// is its reset's first frame, the others its step with the action it was last sent.
struct AsyncModel {
    models: Vec<EnvModel>,
    first_seen: Vec<bool>,
    sent: Vec<i64>,
    k: usize,
}

impl AsyncModel {
    /// `n` envs seeded 10 + i, stacked `k` frames.
    fn new(n: usize, k: usize) -> AsyncModel {
        AsyncModel { models: (0..n as u64).map(|i| EnvModel::new(10 + i)).collect(), first_seen: vec![false; n], sent: vec![0; n], k }
    }

    /// Checks a recv's outcome for its ready `envs`; returns how many of their episodes ended.
    fn check(&mut self, envs: &[usize], outcome: &StepOutcome, round: i64) -> usize {
        let frame_bytes = self.k * FRAME_BYTES;
        let mut final_rows = outcome.final_obs.chunks_exact(frame_bytes);
        let mut ends = 0;
        for &env in envs {
            if !std::mem::replace(&mut self.first_seen[env], true) {
                // Its reset's first frame, stacked k times; no reward, no episode end.
                assert_eq!((outcome.rewards[env], outcome.terminated[env], outcome.truncated[env]), (0.0, false, false));
            } else {
                let (reward, terminated, truncated, ended) = self.models[env].step(self.sent[env], self.k);
                assert_eq!((outcome.rewards[env], outcome.terminated[env], outcome.truncated[env]), (reward, terminated, truncated));
                if let Some((final_stack, _, _)) = ended {
                    assert_eq!(final_rows.next().unwrap(), final_stack.as_slice(), "env {env} round {round}");
                    ends += 1;
                }
            }
            let expected = EnvModel::stack(&self.models[env].frames, self.k);
            assert_eq!(&outcome.obs[env * frame_bytes..][..frame_bytes], expected.as_slice(), "env {env} round {round}");
        }
        assert!(final_rows.next().is_none(), "one final observation per ended episode");
        ends
    }

    /// Every env's action for a send to `envs` in `round` (the others' rows 0), remembered for `check`.
    fn next_actions(&mut self, envs: &[usize], round: i64) -> Vec<i64> {
        let mut values = vec![0i64; self.sent.len()];
        for &env in envs {
            self.sent[env] = (env as i64 + round) % 3;
            values[env] = self.sent[env];
        }
        values
    }
}

/// An async session (option batch_size) of `num_envs` fake envs of `engine`, built directly (so that
/// a session split over processes can be tried).
async fn async_session(
    simulators: &FakeSimulators,
    num_envs: usize,
    batch: i64,
    frame_stack: i64,
    engine: &str,
) -> Result<Session, CoreError> {
    use crate::catalog::{EnvId, Family, OptionValue, BATCH_SIZE, ENGINE};
    let mut options = fake::fake_options(frame_stack);
    options.insert(BATCH_SIZE.to_string(), OptionValue::Int(batch));
    options.insert(ENGINE.to_string(), OptionValue::Str(engine.into()));
    let config = SessionConfig {
        env: EnvId { family: Family::Gym, name: "Fake-v0".into() },
        num_envs,
        seed: 10,
        options,
        frame_stack: frame_stack as usize,
    };
    Session::create(simulators, config).await
}

#[tokio::test]
async fn an_async_session_gives_each_env_its_own_episodes_in_the_order_envs_come_back() {
    // EnvPool's asynchronous mode: recv returns batch_size envs at a time, in whatever order they
    // complete; each env's stack, rewards, episode ends and final observations are still its own.
    let (k, n, batch) = (2usize, 6usize, 2usize);
    let simulators = FakeSimulators::new(1);
    let mut session = async_session(&simulators, n, batch as i64, k as i64, "envpool").await.unwrap();
    assert_eq!(session.async_batch(), Some(batch));
    let sent = |envs: &[usize]| (0..n).map(|env| envs.contains(&env)).collect::<Vec<bool>>();
    let all_actions = |value: i64| actions(&vec![value; n]);
    // Before async_reset nothing steps; the synchronous calls are refused with what to use instead.
    assert!(matches!(session.send(DType::Int64, &[n], &all_actions(0), &sent(&[0])).await, Err(CoreError::NotReset)));
    let refused = session.step(DType::Int64, &[n], &all_actions(0)).await.unwrap_err();
    assert!(refused.to_string().contains("async_reset and stepped with send/recv"), "{refused}");
    session.async_reset(None).await.unwrap();
    let mut model = AsyncModel::new(n, k);
    let mut order = Vec::new();
    let mut ends = 0;
    for round in 0..40 {
        let (ready, outcome) = session.recv().await.unwrap();
        let envs: Vec<usize> = (0..n).filter(|&env| ready[env]).collect();
        assert_eq!(envs.len(), batch, "round {round}");
        order.extend(envs.iter().copied());
        ends += model.check(&envs, &outcome, round);
        let values = model.next_actions(&envs, round);
        session.send(DType::Int64, &[n], &actions(&values), &sent(&envs)).await.unwrap();
        // An env already stepping cannot be sent another action.
        let busy = session.send(DType::Int64, &[n], &all_actions(0), &sent(&envs[..1])).await.unwrap_err();
        assert!(busy.to_string().contains("still stepping"), "{busy}");
    }
    assert!(ends > 0, "the run covers episode ends");
    assert_ne!(order[..n].to_vec(), (0..n).collect::<Vec<_>>(), "envs come back in another order than sent");
    assert_eq!(session.total_env_steps(), 40 * batch as u64 - n as u64);
    session.close().await;
}

#[tokio::test]
async fn an_async_session_refuses_what_would_wait_forever_and_what_it_cannot_keep() {
    let simulators = FakeSimulators::new(1);
    let mut session = async_session(&simulators, 4, 2, 1, "envpool").await.unwrap();
    session.async_reset(Some(3)).await.unwrap();
    session.recv().await.unwrap();
    session.recv().await.unwrap();
    // Nothing stepping: a recv would wait forever; it is refused with what to do.
    let refused = session.recv().await.unwrap_err();
    assert!(refused.to_string().contains("send actions to at least 2 more"), "{refused}");
    let one = (0..4).map(|env| env == 1).collect::<Vec<_>>();
    // A send and recv in one call whose recv could not be answered sends nothing.
    let refused = session.send_recv(DType::Int64, &[4], &actions(&[0, 1, 0, 0]), &one).await.unwrap_err();
    assert!(refused.to_string().contains("send actions to at least 1 more"), "{refused}");
    session.send(DType::Int64, &[4], &actions(&[0, 1, 0, 0]), &one).await.unwrap();
    assert!(session.recv().await.unwrap_err().to_string().contains("at least 1 more"));
    let two = (0..4).map(|env| env == 2).collect::<Vec<_>>();
    let (ready, _) = session.send_recv(DType::Int64, &[4], &actions(&[0, 0, 1, 0]), &two).await.unwrap();
    assert_eq!(ready.iter().filter(|&&ready| ready).count(), 2, "a batch of the two envs stepping");
    assert!(session.send(DType::Int64, &[4], &actions(&[0; 4]), &[false; 4]).await.unwrap_err().to_string().contains("names no env"));
    // Bad actions are refused before anything is sent, as in step.
    assert!(matches!(session.send(DType::Int64, &[4], &actions(&[0, 9, 0, 0]), &one).await, Err(CoreError::InvalidActions(_))));
    session.close().await;
    // A synchronous session has no send/recv, and an async one needs one simulator process.
    let (simulators, manager) = manager(1, limits());
    let id = create(&manager, 2, 0, 1, SessionExtras::default()).await;
    let sync = manager.get(&local(), &id).unwrap();
    let refused = sync.lock().await.recv().await.unwrap_err();
    assert!(refused.to_string().contains("steps every env at once"), "{refused}");
    let split = async_session(&FakeSimulators::new(2), 4, 2, 1, "envpool").await.err().expect("refused");
    assert!(split.to_string().contains("one simulator process"), "{split}");
    drop(simulators);
}

#[tokio::test]
async fn the_native_engines_async_mode_returns_whole_groups_and_keeps_each_envs_episodes() {
    // Groups of batch_size envs, each stepped whole in its worker: recv returns the first group done,
    // send takes whole groups; each env's stack, rewards, ends and final observations are its own.
    let (k, n, batch) = (2usize, 6usize, 2usize);
    let simulators = FakeSimulators::new(2);
    let mut session = async_session(&simulators, n, batch as i64, k as i64, "native").await.unwrap();
    assert_eq!(session.async_batch(), Some(batch));
    let frame_bytes = k * FRAME_BYTES;
    let sent = |envs: &[usize]| (0..n).map(|env| envs.contains(&env)).collect::<Vec<bool>>();
    session.async_reset(None).await.unwrap();
    let mut model = AsyncModel::new(n, k);
    let mut ends = 0;
    let (mut ready, mut outcome) = session.recv().await.unwrap();
    for round in 0..40i64 {
        let envs: Vec<usize> = (0..n).filter(|&env| ready[env]).collect();
        assert_eq!(envs.len(), batch, "round {round}");
        assert!(envs[0].is_multiple_of(batch) && envs[1] == envs[0] + 1, "a whole group: {envs:?}");
        ends += model.check(&envs, &outcome, round);
        // Part of a group is refused, and sends nothing.
        let refused = session.send(DType::Int64, &[n], &actions(&[0; 6]), &sent(&envs[..1])).await.unwrap_err();
        assert!(refused.to_string().contains("send names whole groups"), "{refused}");
        let values = model.next_actions(&envs, round);
        (ready, outcome) = if round % 2 == 0 {
            session.send_recv(DType::Int64, &[n], &actions(&values), &sent(&envs)).await.unwrap()
        } else {
            session.send(DType::Int64, &[n], &actions(&values), &sent(&envs)).await.unwrap();
            session.recv().await.unwrap()
        };
    }
    assert!(ends > 0, "the run covers episode ends");
    assert_eq!(session.total_env_steps(), 40 * batch as u64 - n as u64 + batch as u64);
    // A seeded async reset with steps in flight: every env starts its seed's episode again.
    session.async_reset(Some(10)).await.unwrap();
    for _ in 0..n / batch {
        let (ready, outcome) = session.recv().await.unwrap();
        for env in (0..n).filter(|&env| ready[env]) {
            let fresh = EnvModel::new(10 + env as u64);
            assert_eq!(&outcome.obs[env * frame_bytes..][..frame_bytes], EnvModel::stack(&fresh.frames, k).as_slice());
        }
    }
    assert!(session.recv().await.unwrap_err().to_string().contains("send actions to at least 2 more"));
    session.close().await;
}

#[tokio::test]
async fn batch_size_is_checked_at_create_before_anything_is_built() {
    use crate::catalog::{OptionValue, BATCH_SIZE, ENGINE};
    let (simulators, manager) = manager(1, limits());
    let options = |engine: &str, batch: i64| {
        let mut options = fake::fake_options(1);
        options.insert(ENGINE.to_string(), OptionValue::Str(engine.into()));
        options.insert(BATCH_SIZE.to_string(), OptionValue::Int(batch));
        options
    };
    let create_with = |options: crate::catalog::Options, buffer: Option<BufferRequest>| {
        let manager = &manager;
        async move {
            manager.create_session(&local(), FAKE_ENV, 4, 0, &options, &SessionExtras { buffer, ..SessionExtras::default() }).await
        }
    };
    let refused = create_with(options("envpool", 5), None).await.unwrap_err().to_string();
    assert!(refused.contains("above num_envs 4"), "{refused}");
    let refused = create_with(options("native", 3), None).await.unwrap_err().to_string();
    assert!(refused.contains("must be a multiple of batch_size"), "{refused}");
    let replay = Some(BufferRequest::Replay { capacity: 100 });
    let refused = create_with(options("envpool", 2), replay).await.unwrap_err().to_string();
    assert!(refused.contains("keeps no replay"), "{refused}");
    assert_eq!(simulators.creates(), 0, "a refused session built nothing");
    assert_eq!(manager.list_sessions(&local()).len(), 0);

    // Below num_envs: stepped by send/recv; equal to it (or 0): an ordinary session.
    let info = create_with(options("envpool", 2), None).await.unwrap();
    let session = manager.get(&local(), &info.session_id).unwrap();
    let mut session = session.lock().await;
    assert_eq!(session.async_batch(), Some(2));
    session.async_reset(Some(1)).await.unwrap();
    let (ready, _) = session.recv().await.unwrap();
    assert_eq!(ready.iter().filter(|&&ready| ready).count(), 2);
    drop(session);
    let info = create_with(options("envpool", 4), replay).await.unwrap();
    let session = manager.get(&local(), &info.session_id).unwrap();
    assert_eq!(session.lock().await.async_batch(), None);
}
