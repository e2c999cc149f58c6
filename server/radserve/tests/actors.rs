//! Server-side actors over gRPC, on the fake simulators: SetPolicy checks models at load, the actor
//! steps the session with the policy and records each transition with the version that acted,
//! versions swap between steps, clients' steps are refused while it acts, a policy that turns NaN
//! stops the actor (not the server), and seeds make acting reproducible. Models:
//! server/policy/tests/models (tests/policies.py). The actor's loop alone (scripted policies, the
//! rate limiter, a panic, a close) is tested in core (`core/src/actor/tests.rs`); with the real
//! simulators and a Python learner, in tests/test_actors.py.

mod common;

use std::collections::BTreeMap;
use std::path::Path;
use std::time::{Duration, Instant};

use common::{connect, start_fake_server};
use radserve_core::fake::{self, FAKE_ENV};
use radserve_core::Limits;
use radserve_service::proto::{self, rad_serve_client::RadServeClient};
use tokio_stream::StreamExt;
use tonic::transport::Channel;
use tonic::Code;

/// The server still creates and resets a fake session.
async fn still_serves(client: &mut RadServeClient<Channel>) {
    let id = session(client, 1, 0, replay(10)).await;
    client.reset(proto::ResetRequest { session_id: id, ..Default::default() }).await.expect("the server still serves");
}

fn model(name: &str) -> Vec<u8> {
    std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("../policy/tests/models").join(name)).expect("fixture")
}

async fn session(client: &mut RadServeClient<Channel>, num_envs: u32, seed: u64, replay: proto::ReplayOptions) -> String {
    let request = proto::CreateSessionRequest { env_id: FAKE_ENV.into(), num_envs, seed, replay: Some(replay), ..Default::default() };
    client.create_session(request).await.unwrap().into_inner().session_id
}

fn replay(capacity: u64) -> proto::ReplayOptions {
    proto::ReplayOptions { capacity, rollout_steps: 0 }
}

async fn set_policy(client: &mut RadServeClient<Channel>, id: &str, name: &str, version: u32) -> Result<proto::SetPolicyResponse, tonic::Status> {
    let request = proto::SetPolicyRequest {
        session_id: id.into(),
        model: model(name),
        head: proto::PolicyHead::Categorical as i32,
        version,
        noise: None,
    };
    client.set_policy(request).await.map(tonic::Response::into_inner)
}

async fn describe(client: &mut RadServeClient<Channel>, id: &str) -> proto::SessionInfo {
    client.describe_session(proto::DescribeSessionRequest { session_id: id.into() }).await.unwrap().into_inner()
}

/// Waits until the session's actor satisfies `done` (Describe's acting info).
async fn wait_acting(client: &mut RadServeClient<Channel>, id: &str, done: impl Fn(&proto::ActingInfo) -> bool) -> proto::ActingInfo {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let acting = describe(client, id).await.acting.expect("acting info");
        if done(&acting) {
            return acting;
        }
        assert!(Instant::now() < deadline, "the actor never got there: {acting:?}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// The small fields of `batches` batches, each as field -> little-endian bytes.
async fn batches(client: &mut RadServeClient<Channel>, request: proto::SampleBatchesRequest) -> Vec<BTreeMap<String, Vec<u8>>> {
    let mut chunks = client.sample_batches(request).await.unwrap().into_inner();
    let mut out: BTreeMap<u64, BTreeMap<String, Vec<u8>>> = BTreeMap::new();
    while let Some(chunk) = chunks.next().await {
        let chunk = chunk.unwrap();
        out.entry(chunk.batch_index).or_default().entry(chunk.field).or_default().extend_from_slice(&chunk.data);
    }
    out.into_values().collect()
}

fn ints<const N: usize>(bytes: &[u8]) -> Vec<i64> {
    bytes
        .chunks(N)
        .map(|b| if N == 4 { i64::from(i32::from_le_bytes(b.try_into().unwrap())) } else { i64::from_le_bytes(b.try_into().unwrap()) })
        .collect()
}

fn floats(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_actor_steps_with_the_policy_and_records_its_version() {
    let (server, _simulators) = start_fake_server(Limits::default(), 2).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    // Fake frames start with the env's seed, so pick_first_byte acts (seed + env) mod 3 in env i.
    let id = session(&mut client, 3, 10, replay(200)).await;
    let status = client.start_acting(proto::StartActingRequest { session_id: id.clone(), ..Default::default() }).await.unwrap_err();
    assert_eq!(status.code(), Code::FailedPrecondition);
    assert!(status.message().contains("SetPolicy before StartActing"), "{}", status.message());
    let loaded = set_policy(&mut client, &id, "pick_first_byte.onnx", 1).await.unwrap();
    assert!(loaded.ops.contains(&"Slice".to_string()) && loaded.opset == 17 && !loaded.has_value, "{loaded:?}");
    for rate in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e300] {
        let bad = proto::StartActingRequest { session_id: id.clone(), steps_per_second: Some(rate), ..Default::default() };
        let status = client.start_acting(bad).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "steps_per_second {rate}: {status:?}");
    }
    let start = proto::StartActingRequest { session_id: id.clone(), random_steps: 6, ..Default::default() };
    assert_eq!(client.start_acting(start.clone()).await.unwrap().into_inner().state, "acting");
    let twice = client.start_acting(start).await.unwrap_err();
    assert_eq!(twice.code(), Code::FailedPrecondition);
    // A client's step is refused while the actor acts, with what to do instead.
    let step = proto::StepRequest {
        session_id: id.clone(),
        actions: Some(proto::Tensor { dtype: proto::DType::DtypeInt64 as i32, shape: vec![3], data: vec![0u8; 24].into() }),
        ..Default::default()
    };
    let refused = client.step(step.clone()).await.unwrap_err();
    assert_eq!(refused.code(), Code::FailedPrecondition);
    assert!(refused.message().contains("StopActing"), "{}", refused.message());
    let reset = client.reset(proto::ResetRequest { session_id: id.clone(), ..Default::default() }).await.unwrap_err();
    assert_eq!(reset.code(), Code::FailedPrecondition);
    let acting = wait_acting(&mut client, &id, |acting| acting.env_steps >= 60 && acting.episodes >= 3).await;
    assert_eq!((acting.policy_version, acting.acting_version, acting.head.as_str()), (Some(1), Some(1), "categorical"));
    assert!(!acting.recent_returns.is_empty());
    // Each return names its env: seeds 10, 11, 12 end their episodes every 4, 5 and 3 steps.
    assert_eq!(acting.recent_envs.len(), acting.recent_returns.len());
    let ended = |env: u32| acting.recent_envs.iter().filter(|&&e| e == env).count();
    assert!(ended(0) > 0 && ended(1) > 0 && ended(2) > ended(1) && ended(0) + ended(1) + ended(2) == acting.recent_envs.len(),
            "{:?}", acting.recent_envs);
    let sample = proto::SampleBatchesRequest { session_id: id.clone(), batch_size: 32, max_batches: Some(4), ..Default::default() };
    let mut versions = std::collections::BTreeSet::new();
    for batch in batches(&mut client, sample).await {
        let env = ints::<4>(&batch["env_index"]);
        let action = ints::<8>(&batch["action"]);
        let step_index = ints::<8>(&batch["step_index"]);
        for (i, version) in ints::<4>(&batch["policy_version"]).into_iter().enumerate() {
            versions.insert(version);
            // The two random steps (6 env steps over 3 envs) carry no version; the rest version 1 and
            // the action the policy must have taken.
            if step_index[i] < 2 {
                assert_eq!(version, -1, "random step {}", step_index[i]);
            } else {
                assert_eq!(version, 1);
                assert_eq!(action[i], (10 + env[i]) % 3, "env {} at step {}", env[i], step_index[i]);
            }
        }
    }
    assert!(versions.contains(&1), "{versions:?}");
    let stopped = client.stop_acting(proto::StopActingRequest { session_id: id.clone() }).await.unwrap().into_inner();
    assert_eq!(stopped.state, "stopped");
    // Stopped, the session is the client's again.
    client.step(step).await.expect("a step after StopActing");
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_new_version_is_taken_between_steps_and_versions_must_grow() {
    let (server, _simulators) = start_fake_server(Limits::default(), 1).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    // Paced, so that the buffer still holds version 3's transitions when it is sampled.
    let id = session(&mut client, 2, 0, replay(20_000)).await;
    set_policy(&mut client, &id, "categorical_fake.onnx", 3).await.unwrap();
    let start = proto::StartActingRequest { session_id: id.clone(), steps_per_second: Some(2000.0), ..Default::default() };
    client.start_acting(start).await.unwrap();
    wait_acting(&mut client, &id, |acting| acting.env_steps >= 20).await;
    let stale = set_policy(&mut client, &id, "categorical_fake.onnx", 3).await.unwrap_err();
    assert_eq!(stale.code(), Code::FailedPrecondition);
    assert!(stale.message().contains("not newer"), "{}", stale.message());
    set_policy(&mut client, &id, "pick_first_byte.onnx", 4).await.unwrap();
    // Enough transitions for the batches below (their min_size is the batch size), whatever the
    // moment the swap happened.
    let acting = wait_acting(&mut client, &id, |acting| acting.acting_version == Some(4) && acting.env_steps >= 200).await;
    assert_eq!(acting.policy_version, Some(4));
    client.stop_acting(proto::StopActingRequest { session_id: id.clone() }).await.unwrap();
    // Every recorded transition was acted by one whole version: 4's are pick_first_byte's actions.
    let sample = proto::SampleBatchesRequest { session_id: id.clone(), batch_size: 64, max_batches: Some(3), ..Default::default() };
    let mut seen = std::collections::BTreeSet::new();
    for batch in batches(&mut client, sample).await {
        let env = ints::<4>(&batch["env_index"]);
        let action = ints::<8>(&batch["action"]);
        for (i, version) in ints::<4>(&batch["policy_version"]).into_iter().enumerate() {
            seen.insert(version);
            if version == 4 {
                assert_eq!(action[i], env[i] % 3);
            }
        }
    }
    assert!(seen.contains(&3) && seen.contains(&4), "{seen:?}");
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_models_are_refused_at_set_policy_with_the_reason() {
    let (server, _simulators) = start_fake_server(Limits::default(), 1).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let id = session(&mut client, 2, 0, replay(50)).await;
    let refused = |result: Result<proto::SetPolicyResponse, tonic::Status>| {
        let status = result.expect_err("refused");
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
        status.message().to_string()
    };
    let garbage = proto::SetPolicyRequest {
        session_id: id.clone(),
        model: b"\x08\x07not a model".to_vec(),
        head: proto::PolicyHead::Categorical as i32,
        version: 1,
        noise: None,
    };
    assert!(refused(client.set_policy(garbage.clone()).await.map(tonic::Response::into_inner)).contains("not an ONNX model"));
    assert!(refused(set_policy(&mut client, &id, "random_op_fake.onnx", 1).await).contains("RandomNormalLike"));
    assert!(refused(set_policy(&mut client, &id, "external_fake.onnx", 1).await).contains("external data"));
    let gaussian = proto::SetPolicyRequest {
        model: model("categorical_fake.onnx"),
        head: proto::PolicyHead::GaussianTanh as i32,
        ..garbage.clone()
    };
    assert!(refused(client.set_policy(gaussian).await.map(tonic::Response::into_inner)).contains("use categorical"));
    let no_head = proto::SetPolicyRequest { head: 0, ..garbage.clone() };
    assert!(refused(client.set_policy(no_head).await.map(tonic::Response::into_inner)).contains("head must be"));
    let state_model = proto::SetPolicyRequest { model: model("gaussian_3x2.onnx"), ..garbage.clone() };
    let message = refused(client.set_policy(state_model).await.map(tonic::Response::into_inner));
    assert!(message.contains("does not take this session's observations"), "{message}");
    // Above the server's limit: refused before anything is parsed.
    let large = proto::SetPolicyRequest { model: vec![0u8; (64 << 20) + 1], ..garbage };
    assert!(refused(client.set_policy(large).await.map(tonic::Response::into_inner)).contains("at most"));
    // Nothing was set: the session has no policy and still steps for its client.
    assert!(describe(&mut client, &id).await.acting.is_none());
    still_serves(&mut client).await;
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_policy_that_turns_nan_stops_its_actor_not_the_server() {
    let (server, _simulators) = start_fake_server(Limits::default(), 1).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    // Finite on the zero observations of the load check; NaN on the first real frame.
    let id = session(&mut client, 2, 0, replay(50)).await;
    set_policy(&mut client, &id, "nan_fake.onnx", 1).await.unwrap();
    client.start_acting(proto::StartActingRequest { session_id: id.clone(), ..Default::default() }).await.unwrap();
    let acting = wait_acting(&mut client, &id, |acting| acting.state != "acting").await;
    assert_eq!(acting.state, "failed");
    assert!(acting.error.contains("not finite") && acting.error.contains("NaN"), "{}", acting.error);
    assert_eq!(server.manager.metrics().acting.failures.load(std::sync::atomic::Ordering::Relaxed), 1);
    // The session is its client's again, and the server serves everyone.
    client.reset(proto::ResetRequest { session_id: id.clone(), ..Default::default() }).await.expect("reset after the failure");
    still_serves(&mut client).await;
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}

/// Two sessions of the same seed acting with the same policy from the same seed record the same
/// actions (the categorical head draws from the actor's generator), with log-probabilities and
/// values in their rollouts.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn acting_is_reproducible_from_its_seed() {
    let (server, _simulators) = start_fake_server(Limits::default(), 2).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let mut rollouts = Vec::new();
    for seed in [5, 5, 6] {
        let id = session(&mut client, 3, 1, proto::ReplayOptions { capacity: 0, rollout_steps: 10 }).await;
        set_policy(&mut client, &id, "categorical_fake.onnx", 1).await.unwrap();
        let start = proto::StartActingRequest { session_id: id.clone(), seed: Some(seed), max_env_steps: Some(30), ..Default::default() };
        client.start_acting(start).await.unwrap();
        let acting = wait_acting(&mut client, &id, |acting| acting.state != "acting").await;
        assert_eq!((acting.state.as_str(), acting.env_steps), ("stopped", 30));
        let request = proto::SampleBatchesRequest {
            session_id: id,
            batch_size: 30,
            source: proto::BatchSource::SourceRollout as i32,
            ..Default::default()
        };
        let batch = batches(&mut client, request).await.remove(0);
        let (t, env, action) = (ints::<4>(&batch["t"]), ints::<4>(&batch["env_index"]), ints::<8>(&batch["action"]));
        let log_prob = floats(&batch["log_prob"]);
        assert!(log_prob.iter().all(|p| *p < 0.0 && p.is_finite()), "{log_prob:?}");
        assert!(floats(&batch["value"]).iter().any(|v| *v != 0.0));
        let mut rows: Vec<(i64, i64, i64)> = (0..30).map(|i| (t[i], env[i], action[i])).collect();
        rows.sort();
        rollouts.push(rows);
    }
    assert_eq!(rollouts[0], rollouts[1]);
    assert_ne!(rollouts[0], rollouts[2]);
    assert_eq!(fake::FRAME_BYTES, 4);
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn closing_an_acting_session_stops_its_actor() {
    let (server, simulators) = start_fake_server(Limits::default(), 1).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let id = session(&mut client, 2, 0, replay(50)).await;
    set_policy(&mut client, &id, "categorical_fake.onnx", 1).await.unwrap();
    client.start_acting(proto::StartActingRequest { session_id: id.clone(), ..Default::default() }).await.unwrap();
    wait_acting(&mut client, &id, |acting| acting.env_steps > 10).await;
    client.close_session(proto::CloseSessionRequest { session_id: id, discard_snapshot: false }).await.unwrap();
    let steps = simulators.steps();
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(simulators.steps(), steps, "the actor went on stepping a closed session");
    assert_eq!(simulators.groups_alive(), 0);
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}
