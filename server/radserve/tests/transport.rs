//! The gRPC transport over the fake simulators: every kind of core failure reaches the client with
//! its documented code, faults in a simulator end episodes as the proto says, and batches stream from
//! a fake session's replay. No worker process, no Python: these run in well under a second.

mod common;

use common::{connect, start_fake_server};
use radserve_core::fake::{self, FAKE_ENV};
use radserve_core::Limits;
use radserve_service::proto::{self, rad_serve_client::RadServeClient};
use tokio_stream::StreamExt;
use tonic::Code;

fn int64_tensor(values: &[i64]) -> proto::Tensor {
    proto::Tensor {
        dtype: proto::DType::DtypeInt64 as i32,
        shape: vec![values.len() as i64],
        data: values.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>().into(),
    }
}

fn create(num_envs: u32, capacity: u64) -> proto::CreateSessionRequest {
    proto::CreateSessionRequest {
        env_id: FAKE_ENV.into(),
        num_envs,
        seed: 4,
        replay: (capacity > 0).then_some(proto::ReplayOptions { capacity, ..Default::default() }),
        ..Default::default()
    }
}

/// A fake session of 2 envs with a replay buffer, reset and stepped `steps` times with `actions`.
async fn session_with_transitions(client: &mut RadServeClient<tonic::transport::Channel>, steps: usize, actions: [i64; 2]) -> String {
    let id = client.create_session(create(2, 100)).await.unwrap().into_inner().session_id;
    client.reset(proto::ResetRequest { session_id: id.clone(), seed: None, ..Default::default() }).await.unwrap();
    for _ in 0..steps {
        client.step(proto::StepRequest { session_id: id.clone(), actions: Some(int64_tensor(&actions)), ..Default::default() }).await.unwrap();
    }
    id
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn core_failures_reach_the_client_with_their_codes() {
    let (server, simulators) = start_fake_server(Limits { max_sessions: 2, ..Limits::default() }, 2).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let session = client.create_session(create(4, 0)).await.unwrap().into_inner();
    let id = session.session_id.clone();
    let step = |values: &[i64]| proto::StepRequest { session_id: id.clone(), actions: Some(int64_tensor(values)), ..Default::default() };

    let code = |result: Result<tonic::Response<proto::StepResponse>, tonic::Status>| result.unwrap_err().code();
    assert_eq!(code(client.step(step(&[0; 4])).await), Code::FailedPrecondition, "step before reset");
    client.reset(proto::ResetRequest { session_id: id.clone(), seed: None, ..Default::default() }).await.unwrap();
    assert_eq!(code(client.step(step(&[0, 0, 0, 3])).await), Code::InvalidArgument, "action out of range");
    let unknown = proto::StepRequest { session_id: "s0-nothing".into(), actions: Some(int64_tensor(&[0; 4])), ..Default::default() };
    assert_eq!(code(client.step(unknown).await), Code::NotFound);

    // A lost group ends its episodes, with the reason, inside a successful step.
    simulators.lose_group_of(3);
    let stepped = client.step(step(&[0; 4])).await.unwrap().into_inner();
    let ended: Vec<(u32, bool, String)> =
        stepped.episodes.iter().map(|end| (end.env_index, end.truncated, end.error.clone())).collect();
    assert_eq!(ended, vec![(2, true, "fake worker died".into()), (3, true, "fake worker died".into())]);
    assert_eq!(stepped.final_obs.unwrap().shape, vec![2, 1, 2, 2]);

    // A simulator that fails the call: INTERNAL, and the session asks for a reset.
    simulators.fail_next_step("garbage from the simulator");
    let failed = client.step(step(&[0; 4])).await.unwrap_err();
    assert_eq!(failed.code(), Code::Internal);
    assert!(failed.message().contains("garbage from the simulator"), "{}", failed.message());
    assert_eq!(code(client.step(step(&[0; 4])).await), Code::FailedPrecondition);

    simulators.refuse_next_create("no such option");
    let refused = client.create_session(create(1, 0)).await.unwrap_err();
    assert_eq!(refused.code(), Code::InvalidArgument);
    assert!(refused.message().contains("could not create gym/Fake-v0: no such option"), "{}", refused.message());

    let no_buffer = proto::SampleBatchesRequest { session_id: id.clone(), batch_size: 2, ..Default::default() };
    assert_eq!(client.sample_batches(no_buffer).await.unwrap_err().code(), Code::FailedPrecondition);
    client.create_session(create(1, 0)).await.unwrap();
    assert_eq!(client.create_session(create(1, 0)).await.unwrap_err().code(), Code::ResourceExhausted);

    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
    assert_eq!(simulators.groups_alive(), 0, "shutdown closed every group");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batches_stream_from_a_fake_sessions_replay() {
    let (server, _simulators) = start_fake_server(Limits::default(), 1).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let id = session_with_transitions(&mut client, 10, [1, 2]).await;
    let request = proto::SampleBatchesRequest { session_id: id.clone(), batch_size: 8, max_batches: Some(3), ..Default::default() };
    let mut chunks = client.sample_batches(request).await.unwrap().into_inner();
    let mut batches = std::collections::BTreeMap::<u64, Vec<proto::BatchChunk>>::new();
    while let Some(chunk) = chunks.next().await {
        let chunk = chunk.unwrap();
        batches.entry(chunk.batch_index).or_default().push(chunk);
    }
    assert_eq!(batches.len(), 3);
    for chunks in batches.values() {
        let obs = chunks.iter().find(|chunk| chunk.field == "obs").expect("obs");
        assert_eq!(obs.shape, vec![8, 1, 2, 2]);
        assert!(obs.data.chunks(fake::FRAME_BYTES).all(|frame| frame[3] == fake::MARK), "every frame is a fake frame");
        let rewards = chunks.iter().find(|chunk| chunk.field == "reward").expect("reward");
        let rewards: Vec<f32> = rewards.data.chunks(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
        assert!(rewards.iter().all(|&reward| reward == 2.0 || reward == 3.0), "action + 1: {rewards:?}");
    }
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_ends_when_its_session_is_closed() {
    let (server, _simulators) = start_fake_server(Limits::default(), 1).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let id = session_with_transitions(&mut client, 5, [0, 0]).await;
    let request = proto::SampleBatchesRequest { session_id: id.clone(), batch_size: 4, ..Default::default() };
    let mut chunks = client.sample_batches(request).await.unwrap().into_inner();
    chunks.next().await.unwrap().unwrap();
    client.close_session(proto::CloseSessionRequest { session_id: id, discard_snapshot: false }).await.unwrap();
    // The stream runs on until the close reaches it, then ends with the session's status: it must
    // not keep the closed session's buffer alive.
    let ended = tokio::time::timeout(std::time::Duration::from_secs(10), async {
        loop {
            match chunks.next().await {
                Some(Ok(_)) => continue,
                Some(Err(status)) => return Some(status),
                None => return None,
            }
        }
    })
    .await
    .expect("the stream outlived its session")
    .expect("the stream ends with a status");
    assert_eq!(ended.code(), Code::NotFound);
    assert!(ended.message().contains("it was closed"), "{}", ended.message());
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
    while server.manager.memory().0 > 0 && std::time::Instant::now() < deadline {
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert_eq!(server.manager.memory().0, 0, "the stream's and the session's memory came back");
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unread_stream_stops_keeping_its_session_and_a_read_one_keeps_it() {
    let limits = Limits { session_idle_timeout_s: 1, unread_stream_timeout_s: 2, ..Limits::default() };
    let (server, _simulators) = start_fake_server(limits, 1).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let unread = session_with_transitions(&mut client, 60, [0, 0]).await;
    let request = |id: &str| proto::SampleBatchesRequest { session_id: id.into(), batch_size: 64, ..Default::default() };
    // Taken once, then never read again: its batches back up in flow control and it stops moving.
    let mut unread_client = RadServeClient::new(connect(&server.address).await);
    let mut unread_chunks = unread_client.sample_batches(request(&unread)).await.unwrap().into_inner();
    unread_chunks.next().await.unwrap().unwrap();
    let read = session_with_transitions(&mut client, 60, [1, 1]).await;
    let mut read_chunks = client.sample_batches(request(&read)).await.unwrap().into_inner();
    let started = std::time::Instant::now();
    let mut asked = started;
    let reaped = loop {
        // Read as a learner reads: batch after batch.
        read_chunks.next().await.unwrap().expect("a read stream keeps its session");
        if asked.elapsed() < std::time::Duration::from_millis(1500) {
            continue;
        }
        // Describe renews the unread session's lease: asked only every 1.5 s (past the idle timeout),
        // to learn of the close.
        asked = std::time::Instant::now();
        if let Err(status) = client.describe_session(proto::DescribeSessionRequest { session_id: unread.clone() }).await {
            break status;
        }
        assert!(started.elapsed() < std::time::Duration::from_secs(30), "the unread stream's session was never reaped");
    };
    assert_eq!(reaped.code(), Code::NotFound, "{reaped:?}");
    client.describe_session(proto::DescribeSessionRequest { session_id: read.clone() }).await.expect("the read session lives");
    // The reaped session's stream gave back its memory (its producer and reservation) though its
    // client still has not read: only the read stream's and its session's remain.
    drop(read_chunks);
    client.close_session(proto::CloseSessionRequest { session_id: read, discard_snapshot: false }).await.unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
    while server.manager.memory().0 > 0 && std::time::Instant::now() < deadline {
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert_eq!(server.manager.memory().0, 0, "the unread stream's memory came back");
    drop((unread_chunks, unread_client));
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_says_not_serving_until_the_catalog_is_built() {
    use tonic_health::pb::health_check_response::ServingStatus;
    let simulators = radserve_core::fake::FakeSimulators::new(2);
    simulators.hold_catalog();
    // The first listing after the hold fails: SERVING comes only from the retry.
    simulators.fail_env_names(1);
    let server = common::start_fake_server_on(simulators.clone(), Limits::default(), Default::default()).await;
    let channel = connect(&server.address).await;
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel.clone());
    for _ in 0..10 {
        for service in ["", "radserve.v1.RadServe", "dm_env_rpc.v1.Environment"] {
            let request = tonic_health::pb::HealthCheckRequest { service: service.into() };
            let status = health.check(request).await.unwrap().into_inner().status;
            assert_eq!(status, ServingStatus::NotServing as i32, "{service:?} while the envs are being listed");
        }
        tokio::time::sleep(std::time::Duration::from_millis(30)).await;
    }
    // ServerInfo answers meanwhile.
    let mut client = RadServeClient::new(channel.clone());
    client.server_info(proto::ServerInfoRequest {}).await.unwrap();
    simulators.release_catalog();
    let timeout = std::time::Duration::from_secs(20);
    for service in ["", "radserve.v1.RadServe", "dm_env_rpc.v1.Environment"] {
        assert!(common::wait_health(&channel, service, ServingStatus::Serving, timeout).await, "{service:?} once the catalog is built");
    }
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_says_not_serving_while_a_simulator_is_stuck() {
    use tonic_health::pb::health_check_response::ServingStatus;
    let options = radserve::ServeOptions { worker_stuck_after: std::time::Duration::from_millis(200), ..Default::default() };
    let (server, simulators) = common::start_fake_server_with(Limits::default(), 2, options).await;
    let channel = connect(&server.address).await;
    let wait_for = async |service: &str, wanted: ServingStatus| {
        common::wait_health(&channel, service, wanted, std::time::Duration::from_secs(10)).await
    };
    assert!(wait_for("radserve.v1.RadServe", ServingStatus::Serving).await);
    simulators.set_overdue(vec![1]);
    assert!(wait_for("radserve.v1.RadServe", ServingStatus::NotServing).await, "a stuck worker turns the service NOT_SERVING");
    assert!(wait_for("dm_env_rpc.v1.Environment", ServingStatus::NotServing).await);
    assert!(wait_for("", ServingStatus::Serving).await, "the process itself still serves");
    simulators.set_overdue(Vec::new());
    assert!(wait_for("radserve.v1.RadServe", ServingStatus::Serving).await, "SERVING again once no worker is stuck");
    assert!(wait_for("dm_env_rpc.v1.Environment", ServingStatus::Serving).await);
    let _ = server.stop.send(());
    server.task.await.unwrap().unwrap();
}
