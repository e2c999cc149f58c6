//! The manager's policy against the fake simulators: limits refused before anything is built,
//! the memory budget, idle sessions reaped and held ones kept, sessions owned by their creator with
//! quotas per principal. End to end over gRPC: server/radserve/tests/security.rs and hardening.rs,
//! tests/test_security.py and test_hardening.py. Sessions themselves are tested in
//! `session/tests.rs`, snapshots in `manager/snapshot_tests.rs`.

use crate::error::CoreError;
use crate::fake::{self, FAKE_ENV};
use crate::manager::{BufferRequest, Limits, SessionExtras};
use crate::principal::{Principal, PrincipalLimits, Role};
use crate::test_support::*;

#[tokio::test]
async fn limits_refuse_before_anything_is_built_and_closing_returns_everything() {
    let limits = Limits { max_sessions: 3, max_envs_per_session: 8, max_total_envs: 12, ..limits() };
    let (simulators, manager) = manager(2, limits);
    let baseline = manager.memory().0;
    let no_extras = SessionExtras::default;

    let too_many = manager.create_session(&local(), FAKE_ENV, 9, 0, &fake::fake_options(1), &no_extras()).await.unwrap_err();
    // Larger than any session may be: no retry can succeed (INVALID_ARGUMENT), unlike the limits
    // that what is open now reaches (RESOURCE_EXHAUSTED).
    assert!(matches!(&too_many, CoreError::TooLarge(m) if m.contains("limit of 8 environments per session")), "{too_many}");
    let zero = manager.create_session(&local(), FAKE_ENV, 0, 0, &fake::fake_options(1), &no_extras()).await.unwrap_err();
    assert!(matches!(zero, CoreError::InvalidSession(_)));
    let unknown = manager.create_session(&local(), "gym/Fak-v0", 1, 0, &fake::fake_options(1), &no_extras()).await.unwrap_err();
    assert!(matches!(&unknown, CoreError::UnknownEnv { suggestions, .. } if suggestions == &["gym/Fake-v0"]), "{unknown}");
    simulators.refuse_next_create("no such option in the simulator");
    let refused = manager.create_session(&local(), FAKE_ENV, 2, 0, &fake::fake_options(1), &no_extras()).await.unwrap_err();
    assert!(matches!(&refused, CoreError::CreateFailed { env_id, .. } if env_id == FAKE_ENV), "{refused}");
    assert_eq!(simulators.groups_alive(), 0);
    assert_eq!(manager.memory().0, baseline, "a refused request reserves nothing");

    let first = create(&manager, 8, 0, 1, no_extras()).await;
    let second = create(&manager, 3, 0, 1, no_extras()).await;
    let over_total = manager.create_session(&local(), FAKE_ENV, 2, 0, &fake::fake_options(1), &no_extras()).await.unwrap_err();
    assert!(matches!(&over_total, CoreError::OverLimit(m) if m.contains("above its limit of 12")), "{over_total}");
    create(&manager, 1, 0, 1, no_extras()).await;
    let over_sessions = manager.create_session(&local(), FAKE_ENV, 1, 0, &fake::fake_options(1), &no_extras()).await.unwrap_err();
    assert!(matches!(&over_sessions, CoreError::OverLimit(m) if m.contains("already hosts 3 sessions")), "{over_sessions}");
    assert_eq!(simulators.groups_alive(), 2 + 2 + 1);
    for error in [&too_many, &zero, &unknown, &refused, &over_total, &over_sessions] {
        assert!(!error.to_string().contains("  "), "a message continued across lines keeps its indentation: {error}");
    }
    for id in [&first, &second] {
        manager.close_session(&local(), id).await.unwrap();
    }
    manager.shutdown().await;
    assert_eq!(simulators.groups_alive(), 0, "every group was closed");
    assert_eq!(manager.memory().0, baseline, "every reservation came back");
    assert!(matches!(manager.get(&local(), &first), Err(CoreError::UnknownSession(_))));
}

#[tokio::test]
async fn the_memory_budget_refuses_what_would_not_fit() {
    let (simulators, manager) = manager(1, limits());
    let extras = |capacity| SessionExtras { buffer: Some(BufferRequest::Replay { capacity }), observation_view: None, name: None };
    // 16 fake envs at 2 MiB each take half of the 64 MiB budget.
    let first = manager.create_session(&local(), FAKE_ENV, 16, 0, &fake::fake_options(1), &extras(100_000)).await.unwrap();
    let creates = simulators.creates();
    let envs_refused = manager.create_session(&local(), FAKE_ENV, 16, 0, &fake::fake_options(1), &extras(10)).await.unwrap_err();
    assert!(
        matches!(&envs_refused, CoreError::OutOfMemory(m) if m.contains("16 envs of gym/Fake-v0") && m.contains("limits.memory_bytes")),
        "{envs_refused}"
    );
    assert_eq!(simulators.creates(), creates, "envs that do not fit are refused before the simulators are asked");
    // These envs fit; their replay buffer, known only once they are built, does not.
    let replay_refused = manager.create_session(&local(), FAKE_ENV, 8, 0, &fake::fake_options(1), &extras(1_000_000)).await.unwrap_err();
    assert!(
        matches!(&replay_refused, CoreError::OutOfMemory(m) if m.contains("a replay buffer of 1000000 transitions")),
        "{replay_refused}"
    );
    assert_eq!(simulators.groups_alive(), 1, "what was built for the refused session was closed");
    manager.close_session(&local(), &first.session_id).await.unwrap();
    assert_eq!(manager.memory().0, 0);
}

#[tokio::test]
async fn idle_sessions_are_reaped_and_held_ones_are_not() {
    let (simulators, manager) = manager(1, Limits { session_idle_timeout_s: 1, ..limits() });
    let idle = create(&manager, 1, 0, 1, SessionExtras::default()).await;
    let held = create(&manager, 1, 0, 1, SessionExtras::default()).await;
    let hold = manager.hold(&local(), &held).unwrap();
    tokio::time::sleep(std::time::Duration::from_millis(1100)).await;
    assert_eq!(manager.reap_idle().await, vec![idle.clone()]);
    assert!(matches!(manager.describe(&local(), &idle).await, Err(CoreError::UnknownSession(_))));
    assert_eq!(simulators.groups_alive(), 1);
    drop(hold);
    assert!(manager.reap_idle().await.is_empty(), "releasing the hold renews the lease");
    manager.close_session(&local(), &held).await.unwrap();
}

#[tokio::test]
async fn a_hold_that_stops_moving_stops_keeping_its_session() {
    use futures_util::FutureExt;
    let (_, sessions) = manager(1, Limits { session_idle_timeout_s: 1, unread_stream_timeout_s: 2, ..limits() });
    let unread = create(&sessions, 1, 0, 1, SessionExtras::default()).await;
    let read = create(&sessions, 1, 0, 1, SessionExtras::default()).await;
    let unread_hold = sessions.hold(&local(), &unread).unwrap();
    let read_hold = sessions.hold(&local(), &read).unwrap();
    let progress = read_hold.progress();
    for _ in 0..2 {
        tokio::time::sleep(std::time::Duration::from_millis(700)).await;
        progress.mark(); // a batch taken by the client
        assert!(sessions.reap_idle().await.is_empty(), "holds within the unread bound keep their sessions");
    }
    // Past 2 s without progress, the unread stream's session is idle since its last use (over 1 s);
    // the read one moved 0.8 s ago.
    tokio::time::sleep(std::time::Duration::from_millis(800)).await;
    assert_eq!(sessions.reap_idle().await, vec![unread.clone()]);
    assert!(unread_hold.session_closed().now_or_never().is_some(), "the stream learns its session was closed");
    drop((unread_hold, read_hold));
    sessions.close_session(&local(), &read).await.unwrap();

    // 0: an open stream holds its session however long it is unread (the old rule).
    let (_, sessions) = manager(1, Limits { session_idle_timeout_s: 1, unread_stream_timeout_s: 0, ..limits() });
    let held = create(&sessions, 1, 0, 1, SessionExtras::default()).await;
    let _hold = sessions.hold(&local(), &held).unwrap();
    tokio::time::sleep(std::time::Duration::from_millis(1100)).await;
    assert!(sessions.reap_idle().await.is_empty());
}

#[tokio::test]
async fn sessions_belong_to_their_creator_and_quotas_hold_per_principal() {
    let (_, manager) = manager(2, limits());
    let quota = PrincipalLimits { max_sessions: Some(2), max_envs: Some(3), memory_bytes: Some(12 << 20) };
    let alice = Principal::new("alice", Role::User, quota);
    let bob = Principal::new("bob", Role::User, PrincipalLimits::default());
    let ops = Principal::new("ops", Role::Admin, PrincipalLimits::default());
    let options = fake::fake_options(1);
    let no_extras = SessionExtras::default;
    let mine = manager.create_session(&alice, FAKE_ENV, 2, 0, &options, &no_extras()).await.unwrap().session_id;

    // Another principal cannot tell the session from one never created.
    let never = "s999-0000000000000000";
    for id in [mine.as_str(), never] {
        let unknown = |result: Result<(), CoreError>| assert!(matches!(result, Err(CoreError::UnknownSession(_))), "{id}");
        unknown(manager.get(&bob, id).map(drop));
        unknown(manager.hold(&bob, id).map(drop));
        unknown(manager.describe(&bob, id).await.map(drop));
        unknown(manager.replay_source(&bob, id).await.map(drop));
        unknown(manager.close_session(&bob, id).await);
    }
    assert!(manager.list_sessions(&bob).is_empty());
    let dashboard = Principal::new("dashboard", Role::Monitor, PrincipalLimits::default());
    assert_eq!(manager.list_sessions(&dashboard).len(), 1);
    assert_eq!(manager.describe(&dashboard, &mine).await.unwrap().session_id, mine);
    assert!(matches!(manager.get(&dashboard, &mine), Err(CoreError::UnknownSession(_))), "a monitor only looks");
    let listed = manager.list_sessions(&ops);
    assert_eq!((listed.len(), listed[0].owner.as_str()), (1, "alice"));
    manager.get(&alice, &mine).unwrap().lock().await.reset(None).await.unwrap();

    // Alice's limits: envs, then memory, then sessions; bob is not held back by them.
    let over_envs = manager.create_session(&alice, FAKE_ENV, 2, 0, &options, &no_extras()).await.unwrap_err();
    assert!(over_envs.to_string().contains("principal 'alice'") && over_envs.to_string().contains("max_envs"), "{over_envs}");
    assert!(matches!(over_envs, CoreError::OverLimit(_)), "fits her quota once she closes a session: {over_envs}");
    let never_fits = manager.create_session(&alice, FAKE_ENV, 7, 0, &options, &no_extras()).await.unwrap_err();
    assert!(matches!(never_fits, CoreError::TooLarge(_)), "more envs (and memory) than her whole quota: {never_fits}");
    let over_memory = manager.reserve_memory(&alice, 10 << 20, "a channel").unwrap_err();
    assert!(matches!(over_memory, CoreError::OverLimit(_)) && over_memory.to_string().contains("quota"), "{over_memory}");
    let above_quota = manager.reserve_memory(&alice, 20 << 20, "a channel").unwrap_err();
    assert!(matches!(above_quota, CoreError::TooLarge(_)) && above_quota.to_string().contains("whole memory quota"), "{above_quota}");
    manager.create_session(&alice, FAKE_ENV, 1, 0, &options, &no_extras()).await.unwrap();
    let over_sessions = manager.create_session(&alice, FAKE_ENV, 1, 0, &options, &no_extras()).await.unwrap_err();
    assert!(over_sessions.to_string().contains("max_sessions"), "{over_sessions}");
    manager.create_session(&bob, FAKE_ENV, 4, 0, &options, &no_extras()).await.unwrap();

    // An admin closes alice's session, which frees her quota.
    manager.close_session(&ops, &mine).await.unwrap();
    assert!(matches!(manager.get(&alice, &mine), Err(CoreError::UnknownSession(_))));
    manager.create_session(&alice, FAKE_ENV, 2, 0, &options, &no_extras()).await.unwrap();
    manager.shutdown().await;
    assert_eq!(manager.memory().0, 0, "every reservation, quota included, came back");
}
