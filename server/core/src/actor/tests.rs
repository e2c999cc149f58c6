//! The server-side actor against the fake simulators, with scripted policies run in the server (no
//! ONNX Runtime): a new version taken between two steps, never within one; the rate limiter's bound
//! on inserts, released by samples; a panic in the loop ending as a failed actor whose session
//! clients step again; a session closed while its actor acts or waits. The same actor with real
//! policies in their runtime processes is tested end to end in `server/radserve/tests/actors.rs`
//! and `tests/test_actors.py`.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use radserve_policy::{Acted, PolicyError};
use radserve_replay::TransitionMetadata;

use super::{ActingRequest, ActingState, ActingStatus, HeldPolicy};
use crate::fake::{self, FakeSimulators, FAKE_ENV};
use crate::manager::{BufferRequest, Limits, SessionExtras, SessionManager};
use crate::principal::Principal;
use crate::space::DType;

/// A policy as a rule: called with the observations and the session's env steps, it returns each
/// env's action (the fake's Discrete(3), as int64).
pub(crate) struct Scripted {
    rule: Box<Rule>,
}

type Rule = dyn FnMut(&[u8], u64) -> Vec<i64> + Send;

impl Scripted {
    fn new(rule: impl FnMut(&[u8], u64) -> Vec<i64> + Send + 'static) -> Scripted {
        Scripted { rule: Box::new(rule) }
    }

    pub(crate) fn act(&mut self, obs: &[u8], env_steps: u64) -> Result<Acted, PolicyError> {
        let actions = (self.rule)(obs, env_steps);
        let log_prob = vec![-1.0; actions.len()];
        Ok(Acted { actions: actions.iter().flat_map(|action| action.to_le_bytes()).collect(), log_prob, value: None })
    }
}

fn local() -> Principal {
    Principal::local()
}

fn constant(num_envs: usize, action: i64) -> Scripted {
    Scripted::new(move |_, _| vec![action; num_envs])
}

async fn session(num_envs: usize, buffer: BufferRequest) -> (SessionManager, String) {
    let manager = SessionManager::new(FakeSimulators::new(1), Limits { session_idle_timeout_s: 0, ..Limits::default() });
    let extras = SessionExtras { buffer: Some(buffer), observation_view: None, name: None };
    let info = manager.create_session(&local(), FAKE_ENV, num_envs, 3, &fake::fake_options(2), &extras).await.unwrap();
    (manager, info.session_id)
}

/// Waits (on the runtime's clock) until the actor's status satisfies `done`.
async fn until(manager: &SessionManager, id: &str, done: impl Fn(&ActingStatus) -> bool) -> ActingStatus {
    let slot = manager.actor_slot(&local(), id);
    tokio::time::timeout(Duration::from_secs(60), async {
        loop {
            let status = slot.status();
            if done(&status) {
                return status;
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    })
    .await
    .unwrap_or_else(|_| panic!("the actor never got there: {:?}", slot.status()))
}

fn inserts(manager: &SessionManager, id: &str) -> u64 {
    let session = manager.get(&local(), id).unwrap();
    let session = session.try_lock().expect("the session between two steps");
    let replay = session.replay().unwrap().read().unwrap();
    replay.counters().inserts
}

#[tokio::test]
async fn a_new_version_is_taken_between_two_steps_never_within_one() {
    let (num_envs, steps) = (3, 40u64);
    let (manager, id) = session(num_envs, BufferRequest::Rollout { steps: steps as usize }).await;
    let slot = manager.actor_slot(&local(), &id);
    // Version 1 installs version 2 while it computes its 10th step's actions: that step still acts
    // with version 1 (what the actor holds), the next with version 2.
    let newer: Arc<Mutex<Option<HeldPolicy>>> = Arc::new(Mutex::new(Some(manager.scripted_policy(&local(), constant(num_envs, 2), 2))));
    let calls = Arc::new(AtomicU64::new(0));
    let first = {
        let (slot, newer, calls) = (slot.clone(), newer.clone(), calls.clone());
        Scripted::new(move |_, _| {
            if calls.fetch_add(1, Ordering::SeqCst) == 9 {
                slot.install(newer.lock().unwrap().take().unwrap(), "scripted");
            }
            vec![1; num_envs]
        })
    };
    slot.install(manager.scripted_policy(&local(), first, 1), "scripted");
    let request = ActingRequest { max_env_steps: Some(steps * num_envs as u64), ..ActingRequest::default() };
    manager.start_acting(&local(), &id, request).await.unwrap();
    let status = until(&manager, &id, |status| status.state == ActingState::Stopped).await;
    assert_eq!((status.env_steps, status.policy_version, status.acting_version), (steps * num_envs as u64, Some(2), Some(2)));
    assert_eq!(calls.load(Ordering::SeqCst), 10, "version 1 acted 10 steps");

    let session = manager.get(&local(), &id).unwrap();
    let session = session.lock().await;
    let replay = session.replay().unwrap().read().unwrap();
    let (table, _) = replay.rollout(steps as usize).unwrap();
    let mut metadata = TransitionMetadata::default();
    replay.gather_metadata(&table, &mut metadata);
    let mut by_step = std::collections::BTreeMap::<u64, Vec<(i32, i64)>>::new();
    for row in 0..metadata.len {
        let action = i64::from_le_bytes(metadata.actions[row * 8..][..8].try_into().unwrap());
        by_step.entry(metadata.step_indices[row]).or_default().push((metadata.policy_versions[row], action));
    }
    let versions: Vec<i32> = by_step
        .values()
        .map(|rows| {
            assert_eq!(rows.len(), num_envs);
            assert!(rows.iter().all(|row| *row == rows[0]), "one version and its actions for every env of a step: {rows:?}");
            let (version, action) = rows[0];
            assert_eq!(action, i64::from(version), "each version's own actions");
            version
        })
        .collect();
    assert_eq!(versions, [vec![1; 10], vec![2; steps as usize - 10]].concat());
}

#[tokio::test]
async fn the_rate_limiter_bounds_inserts_until_samples_release_them() {
    let num_envs = 2;
    let (manager, id) = session(num_envs, BufferRequest::Replay { capacity: 1000 }).await;
    let slot = manager.actor_slot(&local(), &id);
    slot.install(manager.scripted_policy(&local(), constant(num_envs, 0), 1), "scripted");
    // Free up to min_size (20); then inserts * 4 - samples may reach 4 * 20 + 8: 22 inserts.
    let request = ActingRequest { samples_per_insert: Some(4.0), error_buffer: 8.0, min_size: 20, ..ActingRequest::default() };
    manager.start_acting(&local(), &id, request).await.unwrap();
    until(&manager, &id, |status| status.env_steps == 22).await;
    // Held there: nothing but a sample can wake it (the limiter is not polled).
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert_eq!(inserts(&manager, &id), 22);
    assert_eq!(slot.status().state, ActingState::Acting);

    // 8 samples give room for 2 more inserts (one step of both envs), and no more.
    {
        let session = manager.get(&local(), &id).unwrap();
        let replay = session.lock().await.replay().unwrap().clone();
        let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
        replay.write().unwrap().sample(8, &mut rng, &mut Vec::new()).unwrap();
    }
    until(&manager, &id, |status| status.env_steps == 24).await;
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert_eq!(inserts(&manager, &id), 24);
    let status = manager.stop_acting(&local(), &id).await.unwrap();
    assert_eq!((status.state, status.env_steps), (ActingState::Stopped, 24));
    assert!(status.limited_seconds > 0.0);
}

#[tokio::test]
async fn a_panic_in_the_loop_fails_the_actor_and_gives_the_session_back() {
    let num_envs = 2;
    let (manager, id) = session(num_envs, BufferRequest::Replay { capacity: 100 }).await;
    let slot = manager.actor_slot(&local(), &id);
    let panicking = Scripted::new(move |_, env_steps| {
        assert!(env_steps < 6, "a scripted bug at env step {env_steps}");
        vec![0; num_envs]
    });
    slot.install(manager.scripted_policy(&local(), panicking, 1), "scripted");
    manager.start_acting(&local(), &id, ActingRequest::default()).await.unwrap();
    let status = until(&manager, &id, |status| status.state == ActingState::Failed).await;
    assert!(status.error.as_deref().unwrap().contains("internal error"), "{status:?}");
    assert_eq!(status.env_steps, 6);
    let session = manager.get(&local(), &id).unwrap();
    let mut session = session.lock().await;
    assert!(!session.is_acting());
    session.step(DType::Int64, &[num_envs], &[0u8; 16]).await.expect("clients step the session again");
}

#[tokio::test]
async fn closing_a_session_ends_its_actor_acting_or_waiting() {
    let num_envs = 2;
    for limited in [false, true] {
        let (manager, id) = session(num_envs, BufferRequest::Replay { capacity: 100 }).await;
        let slot = manager.actor_slot(&local(), &id);
        slot.install(manager.scripted_policy(&local(), constant(num_envs, 0), 1), "scripted");
        // Limited: it waits on the limiter from 10 transitions on (no learner samples).
        let request = if limited {
            ActingRequest { samples_per_insert: Some(1.0), error_buffer: 0.0, min_size: 10, ..ActingRequest::default() }
        } else {
            ActingRequest::default()
        };
        manager.start_acting(&local(), &id, request).await.unwrap();
        until(&manager, &id, |status| status.env_steps >= 10).await;
        let caller = local();
        tokio::time::timeout(Duration::from_secs(60), manager.close_session(&caller, &id)).await.expect("close returns").unwrap();
        assert_eq!(slot.status().state, ActingState::Stopped, "limited: {limited}");
        assert!(manager.get(&local(), &id).is_err());
    }
}
