//! Named sessions and their replay snapshots through the manager, over the fake simulators: a name is
//! unique per owner while its session lives; a named session's replay comes back in a new manager
//! (a restarted server) created over the same directory, with its counters; a snapshot of another
//! session is set aside or refused as configured; a discarded one is gone.

use std::path::Path;

use crate::error::CoreError;
use crate::fake::{self, FakeSimulators, FAKE_ENV};
use crate::manager::snapshots::owner_dir;
use crate::manager::{BufferRequest, Limits, OnBadSnapshot, ReplayConfig, SessionExtras, SessionInfo, SessionManager};
use crate::principal::{Principal, PrincipalLimits, Role};
use crate::space::DType;

fn manager(dir: Option<&Path>, policy: OnBadSnapshot) -> SessionManager {
    let limits = Limits { memory_bytes: 64 << 20, session_idle_timeout_s: 0, ..Limits::default() };
    let config = ReplayConfig {
        snapshot_dir: dir.map(Path::to_path_buf),
        snapshot_interval_s: 3600.0,
        on_bad_snapshot: policy,
        ..ReplayConfig::default()
    };
    SessionManager::new(FakeSimulators::new(2), limits).with_snapshots(config)
}

fn named(name: &str, capacity: usize) -> SessionExtras {
    SessionExtras { buffer: Some(BufferRequest::Replay { capacity }), observation_view: None, name: Some(name.into()) }
}

async fn create(manager: &SessionManager, caller: &Principal, num_envs: usize, extras: &SessionExtras) -> Result<SessionInfo, CoreError> {
    manager.create_session(caller, FAKE_ENV, num_envs, 3, &fake::fake_options(2), extras).await
}

async fn run(manager: &SessionManager, id: &str, steps: usize) {
    let session = manager.get(&Principal::local(), id).unwrap();
    let mut session = session.lock().await;
    if session.needs_reset() {
        session.reset(None).await.unwrap();
    }
    let num_envs = session.num_envs();
    for step in 0..steps {
        let actions: Vec<u8> = (0..num_envs).flat_map(|env| (((step + env) % 3) as i64).to_le_bytes()).collect();
        session.step(DType::Int64, &[num_envs], &actions).await.unwrap();
    }
}

#[tokio::test]
async fn a_name_is_unique_per_owner_while_its_session_lives() {
    let manager = manager(None, OnBadSnapshot::Empty);
    let local = Principal::local();
    let first = create(&manager, &local, 2, &named("run-1", 100)).await.unwrap();
    assert_eq!(first.name.as_deref(), Some("run-1"));
    let taken = create(&manager, &local, 2, &named("run-1", 100)).await.unwrap_err();
    assert!(matches!(&taken, CoreError::NameTaken(message) if message.contains(&first.session_id)), "{taken}");
    let other = Principal::new("bob", Role::User, PrincipalLimits::default());
    create(&manager, &other, 2, &named("run-1", 100)).await.expect("another owner's names are its own");
    for bad in ["", "../etc", ".hidden", "a/b", "spaces here", &"x".repeat(65)] {
        let error = create(&manager, &local, 2, &named(bad, 100)).await.unwrap_err();
        assert!(matches!(error, CoreError::InvalidSession(_)), "{bad:?}: {error}");
    }
    let runs = manager.list_sessions(&local);
    let runs: Vec<_> = runs.iter().filter(|s| s.name.as_deref() == Some("run-1")).map(|s| s.owner.as_str()).collect();
    assert_eq!(runs, ["local", "bob"]);
    manager.close_session(&local, &first.session_id).await.unwrap();
    create(&manager, &local, 2, &named("run-1", 100)).await.expect("a closed session's name is free");
}

#[tokio::test]
async fn a_named_replay_comes_back_in_a_restarted_server() {
    let dir = tempfile::tempdir().unwrap();
    let local = Principal::local();
    let first = manager(Some(dir.path()), OnBadSnapshot::Empty);
    let info = create(&first, &local, 3, &named("sac", 1000)).await.unwrap();
    let none_yet = info.replay.as_ref().unwrap().snapshot.clone().expect("a named session's replay is snapshotted");
    assert_eq!((none_yet.age, none_yet.disk_bytes, none_yet.restored_transitions), (None, 0, 0));
    run(&first, &info.session_id, 30).await;
    first.snapshot_all(false);
    let described = first.describe(&local, &info.session_id).await.unwrap();
    let snapshot = described.replay.as_ref().unwrap().snapshot.clone().expect("a snapshot");
    assert!(snapshot.disk_bytes > 0 && snapshot.age.is_some() && snapshot.restored_transitions == 0, "{snapshot:?}");
    assert_eq!(snapshot.pending_frames, 0, "the snapshot holds everything recorded");
    let saved = described.replay.unwrap().size;
    assert_eq!(saved, 90);
    // Steps after the last snapshot are lost with the process (the manager is dropped unclosed,
    // as a killed server is).
    run(&first, &info.session_id, 4).await;
    let behind = first.describe(&local, &info.session_id).await.unwrap().replay.unwrap().snapshot.unwrap();
    assert!(behind.pending_frames >= 12, "4 steps of 3 envs (and first frames of episodes) since the snapshot: {behind:?}");
    std::mem::forget(first);

    let second = manager(Some(dir.path()), OnBadSnapshot::Empty);
    let restored = create(&second, &local, 3, &named("sac", 1000)).await.unwrap();
    let replay = restored.replay.clone().unwrap();
    assert_eq!(replay.size, saved, "every snapshotted transition is back before the first step");
    assert_eq!(replay.snapshot.as_ref().unwrap().restored_transitions, saved as u64);
    assert_eq!(restored.total_env_steps, 90, "the session's counters continue");
    run(&second, &restored.session_id, 10).await;
    {
        let session = second.get(&local, &restored.session_id).unwrap();
        let session = session.lock().await;
        let buffer = session.replay().unwrap().read().unwrap();
        assert_eq!(buffer.len(), saved + 30);
        assert!(buffer.steps_recorded() > 30, "step indices continue after the restored ones");
    }
    // A close writes the last snapshot; the next server gets everything.
    second.close_session(&local, &restored.session_id).await.unwrap();
    let third = manager(Some(dir.path()), OnBadSnapshot::Empty);
    let again = create(&third, &local, 3, &named("sac", 1000)).await.unwrap();
    assert_eq!(again.replay.unwrap().size, saved + 30);
    // Discarded: gone, and the next session of the name starts empty.
    third.close_session_with(&local, &again.session_id, true).await.unwrap();
    let fresh = create(&third, &local, 3, &named("sac", 1000)).await.unwrap();
    assert_eq!(fresh.replay.unwrap().size, 0);
}

#[tokio::test]
async fn a_snapshot_of_another_session_is_set_aside_or_refused() {
    let dir = tempfile::tempdir().unwrap();
    let local = Principal::local();
    let first = manager(Some(dir.path()), OnBadSnapshot::Refuse);
    let info = create(&first, &local, 3, &named("sac", 1000)).await.unwrap();
    run(&first, &info.session_id, 10).await;
    first.close_session(&local, &info.session_id).await.unwrap();
    let owner_dir = dir.path().join(owner_dir("local"));
    let listing = || -> Vec<String> {
        let mut names: Vec<String> =
            std::fs::read_dir(&owner_dir).unwrap().map(|entry| entry.unwrap().file_name().to_string_lossy().into_owned()).collect();
        names.sort();
        names
    };

    // Refused: created with 2 envs, the snapshot holds 3; nothing moves.
    let refused = create(&first, &local, 2, &named("sac", 1000)).await.unwrap_err();
    assert!(matches!(&refused, CoreError::BadSnapshot(message) if message.contains("MANIFEST") && message.contains("created as")), "{refused}");
    assert_eq!(listing(), vec!["sac".to_string()]);
    assert_eq!(first.metrics().snapshots().failures.load(std::sync::atomic::Ordering::Relaxed), 1);
    assert!(first.list_sessions(&local).is_empty(), "the refused session left nothing behind");
    create(&first, &local, 3, &named("sac", 1000)).await.expect("the name is free again after a refusal");

    // Set aside: the session starts empty, the old files are kept beside.
    let lenient = manager(Some(dir.path()), OnBadSnapshot::Empty);
    let started = create(&lenient, &local, 2, &named("sac", 1000)).await.unwrap();
    assert_eq!(started.replay.unwrap().size, 0);
    assert_eq!(lenient.metrics().snapshots().failures.load(std::sync::atomic::Ordering::Relaxed), 1, "set aside, and counted");
    let names = listing();
    assert!(names.len() == 1 && names[0].starts_with("sac.rejected-"), "{names:?}");
}

