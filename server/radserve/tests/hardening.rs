//! Hostile requests replayed against the real server (issue: "no request, client or fault can crash,
//! freeze or exhaust the server"). Each test sends what broke an earlier build through the generated
//! stubs and checks both the answer and that the server still serves everyone else. The same
//! hostile messages through grpcio, the client most learners use: tests/test_hardening.py.

mod common;

use std::collections::HashMap;
use std::error::Error as _;
use std::time::{Duration, Instant};

use common::{connect, start_server, start_server_with, still_serves};
use radserve_service::proto::{self, rad_serve_client::RadServeClient};
use radserve_core::Limits;
use tonic::transport::Channel;
use tonic::Code;

fn cartpole(replay: Option<proto::ReplayOptions>) -> proto::CreateSessionRequest {
    proto::CreateSessionRequest { env_id: "gym/CartPole-v1".into(), num_envs: 1, replay, ..Default::default() }
}

fn replay_capacity(capacity: u64) -> Option<proto::ReplayOptions> {
    Some(proto::ReplayOptions { capacity, ..Default::default() })
}

/// A CartPole session with a replay buffer holding a few transitions.
async fn session_with_replay(client: &mut RadServeClient<Channel>) -> String {
    let session = client.create_session(cartpole(replay_capacity(1000))).await.unwrap().into_inner();
    let session_id = session.session_id;
    client.reset(proto::ResetRequest { session_id: session_id.clone(), seed: Some(0), ..Default::default() }).await.unwrap();
    for _ in 0..20 {
        let actions = proto::Tensor {
            dtype: proto::DType::DtypeInt64 as i32,
            shape: vec![1],
            data: 0i64.to_le_bytes().to_vec().into(),
        };
        client.step(proto::StepRequest { session_id: session_id.clone(), actions: Some(actions), ..Default::default() }).await.unwrap();
    }
    session_id
}

fn sample_request(session_id: &str) -> proto::SampleBatchesRequest {
    proto::SampleBatchesRequest { session_id: session_id.into(), batch_size: 4, ..Default::default() }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_sizes_that_overflow_are_refused_and_the_server_lives() {
    let server = start_server(Limits::default()).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    // (capacity + 1) * 45 bytes wraps to 29 bytes in 64 bits: this aborted the server.
    for capacity in [409_927_646_082_434_480u64, u64::MAX, 1 << 41] {
        let status = client.create_session(cartpole(replay_capacity(capacity))).await.unwrap_err();
        // Larger than the server could ever hold: no retry helps (INVALID_ARGUMENT, not RESOURCE_EXHAUSTED).
        assert_eq!(status.code(), Code::InvalidArgument, "capacity {capacity}: {status:?}");
        assert!(status.message().contains("capacity") || status.message().contains("GiB"), "{}", status.message());
    }
    // Rollouts: steps * num_envs and 2 * steps are the products here.
    let rollout = Some(proto::ReplayOptions { rollout_steps: u32::MAX, ..Default::default() });
    let status = client.create_session(proto::CreateSessionRequest { num_envs: 256, ..cartpole(rollout) }).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    still_serves(&mut client).await;
    // Nothing was reserved by the refused requests: the whole budget is still free.
    let info = server.manager.describe(&radserve_core::Principal::local(), &session_with_replay(&mut client).await).await.unwrap();
    assert_eq!(info.replay.unwrap().size, 20);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn huge_text_fields_are_refused_before_any_work() {
    let server = start_server(Limits::default()).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    still_serves(&mut client).await; // the env names are known: the next call does no set-up work
    // 8 MB of unknown env id took 163 s of a tokio worker in edit distances, freezing the server.
    let started = Instant::now();
    let huge = "x".repeat(8 << 20);
    let status = client
        .create_session(proto::CreateSessionRequest { env_id: huge.clone(), num_envs: 1, ..Default::default() })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument, "{}", status.message());
    assert_eq!(status.message(), format!("env_id is {} bytes long; the most accepted is 256", huge.len()));
    // A long id under the cap gets its answer without suggestions work blowing up, clipped.
    let long = format!("gym/{}", "y".repeat(250));
    let status = client
        .create_session(proto::CreateSessionRequest { env_id: long, num_envs: 1, ..Default::default() })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::NotFound);
    assert!(status.message().len() < 400, "{}", status.message());
    // Unknown sessions: a 100 KB id is answered NOT_FOUND with the id clipped (not as a trailer
    // that is too large for clients to read).
    let status = client.describe_session(proto::DescribeSessionRequest { session_id: huge[..100_000].into() }).await.unwrap_err();
    assert_eq!(status.code(), Code::NotFound);
    assert!(status.message().contains("(100000 bytes in all)") && status.message().len() < 300, "{}", status.message());
    // Options: too many, too long a name, too long a value.
    let many: HashMap<String, proto::OptionValue> = (0..1000)
        .map(|i| (format!("option{i}"), proto::OptionValue { value: Some(proto::option_value::Value::BoolValue(true)) }))
        .collect();
    let status = client.create_session(proto::CreateSessionRequest { options: many, ..cartpole(None) }).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().contains("options has 1000 entries; the most accepted is 32"), "{}", status.message());
    let long_value = HashMap::from([(
        "render_profile".to_string(),
        proto::OptionValue { value: Some(proto::option_value::Value::StringValue("z".repeat(1 << 20))) },
    )]);
    let request = proto::CreateSessionRequest { env_id: "dmc/cheetah-run".into(), num_envs: 1, options: long_value, ..Default::default() };
    let status = client.create_session(request).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().len() < 200, "{}", status.message());
    // Views and pipelines in text form are bounded too.
    let request = proto::CreateSessionRequest { observation_view: "center_crop(84)|".repeat(100_000), ..cartpole(None) };
    let status = client.create_session(request).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().starts_with("observation_view is 1600000 bytes long"), "{}", status.message());
    let status = client.list_envs(proto::ListEnvsRequest { prefix: huge[..1000].into() }).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert_eq!(status.message(), "prefix is 1000 bytes long; the most accepted is 256");
    assert!(started.elapsed() < Duration::from_secs(30), "took {:?}", started.elapsed());
    still_serves(&mut client).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_streams_cannot_pass_the_per_session_limit() {
    let server = start_server(Limits { max_streams_per_session: 4, ..Limits::default() }).await;
    let channel = connect(&server.address).await;
    let mut client = RadServeClient::new(channel.clone());
    let session_id = session_with_replay(&mut client).await;
    // 40 at once: the count was checked before any of them was counted (33-40 got through).
    let calls = (0..40).map(|_| {
        let mut client = RadServeClient::new(channel.clone());
        let request = sample_request(&session_id);
        tokio::spawn(async move { client.sample_batches(request).await })
    });
    let mut accepted = Vec::new();
    let mut refused = 0;
    for call in calls.collect::<Vec<_>>() {
        match call.await.unwrap() {
            Ok(stream) => accepted.push(stream.into_inner()),
            Err(status) => {
                assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
                assert!(status.message().contains("already has 4 sample streams open"), "{}", status.message());
                refused += 1;
            }
        }
    }
    assert_eq!((accepted.len(), refused), (4, 36));
    // Closing the streams frees their places.
    drop(accepted);
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let active = server.manager.describe(&radserve_core::Principal::local(), &session_id).await.unwrap().replay.unwrap().active_streams;
        if active == 0 {
            break;
        }
        assert!(Instant::now() < deadline, "{active} streams still counted");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let stream = client.sample_batches(sample_request(&session_id)).await.expect("a place is free again");
    drop(stream);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn amplifying_sizes_are_refused() {
    let server = start_server(Limits::default()).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let session_id = session_with_replay(&mut client).await;
    // 1-byte chunks made ~195 bytes of server memory per tensor byte.
    for chunk_bytes in [1, 1000, u32::MAX] {
        let request = proto::SampleBatchesRequest { chunk_bytes, ..sample_request(&session_id) };
        let status = client.sample_batches(request).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument);
        assert!(status.message().contains("chunk_bytes must be 0"), "{}", status.message());
    }
    // A view 18x the frame on a 16-frame stack: 2.1 GB of observations per Reset.
    let options = HashMap::from([(
        "frame_stack".to_string(),
        proto::OptionValue { value: Some(proto::option_value::Value::IntValue(16)) },
    )]);
    let request = proto::CreateSessionRequest {
        env_id: "procgen/bigfish".into(),
        num_envs: 32,
        options,
        observation_view: "center_translate(1182)".into(),
        ..Default::default()
    };
    let status = client.create_session(request).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(status.message().contains("the most a step may return"), "{}", status.message());
    still_serves(&mut client).await;
}

/// Found by tests/fuzz.rs: a SampleBatchesShared call whose client never sent its `start` held the
/// call for as long as the connection lived.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_shared_sample_stream_that_never_starts_is_ended() {
    let server = start_server(Limits::default()).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let (sender, receiver) = tokio::sync::mpsc::channel::<proto::SharedSampleRequest>(1);
    let started = Instant::now();
    let call = client.sample_batches_shared(tokio_stream::wrappers::ReceiverStream::new(receiver));
    let status = tokio::time::timeout(radserve_service::sample_streams::FIRST_MESSAGE_TIMEOUT * 2, call)
        .await
        .expect("the server ends the call")
        .unwrap_err();
    assert_eq!(status.code(), Code::DeadlineExceeded, "{status:?}");
    assert!(status.message().contains("no SharedSampleRequest with `start` arrived within 10 s"), "{}", status.message());
    assert!(started.elapsed() >= radserve_service::sample_streams::FIRST_MESSAGE_TIMEOUT);
    drop(sender);
    still_serves(&mut client).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pipelines_are_bounded_and_typed_keys_cannot_smuggle_stages() {
    let server = start_server(Limits::default()).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let session_id = session_with_replay(&mut client).await;
    use proto::sample_batches_request::Augmentation;
    let with = |augmentation| proto::SampleBatchesRequest { augmentation: Some(augmentation), ..sample_request(&session_id) };
    // 3000 colour-jitter stages starved every other stream of the augmentation threads.
    let text = vec!["noise"; 3000].join("|");
    let status = client.sample_batches(with(Augmentation::PipelineText(text))).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().contains("at most 1024 bytes"), "{}", status.message());
    let status = client.sample_batches(with(Augmentation::PipelineText(["noise"; 9].join("|")))).await.unwrap_err();
    assert!(status.message().contains("at most 8 stages, got 9"), "{}", status.message());
    let stage = |name: &str, args: &[(&str, f64)]| proto::AugmentationStage {
        name: name.into(),
        args: args.iter().map(|(key, value)| (key.to_string(), *value)).collect(),
    };
    let typed = |stages| Augmentation::Pipeline(proto::AugmentationPipeline { stages });
    // A key that closes the stage and opens another one.
    let smuggled = typed(vec![stage("noise", &[("std=1)|noise(std", 2.0)])]);
    let status = client.sample_batches(with(smuggled)).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().contains("argument names of noise are plain names"), "{}", status.message());
    let status = client.sample_batches(with(typed(vec![stage("noise", &[]); 3000]))).await.unwrap_err();
    assert!(status.message().contains("at most 8 stages, got 3000"), "{}", status.message());
    let fine = client.sample_batches(with(typed(vec![stage("noise", &[("std", 0.5)])]))).await;
    assert!(fine.is_ok(), "{fine:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn abandoned_sessions_are_reaped_and_open_streams_keep_theirs() {
    let server = start_server(Limits { session_idle_timeout_s: 1, ..Limits::default() }).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let abandoned = client.create_session(cartpole(None)).await.unwrap().into_inner().session_id;
    let streamed = session_with_replay(&mut client).await;
    let stream = client.sample_batches(sample_request(&streamed)).await.unwrap().into_inner();
    let used = client.create_session(cartpole(None)).await.unwrap().into_inner().session_id;
    let listed = client.list_sessions(proto::ListSessionsRequest {}).await.unwrap().into_inner();
    assert_eq!(listed.idle_timeout_seconds, 1.0);
    assert_eq!(listed.sessions.len(), 3);
    let summary = listed.sessions.iter().find(|s| s.session_id == streamed).unwrap();
    assert_eq!((summary.env_id.as_str(), summary.num_envs, summary.open_streams), ("gym/CartPole-v1", 1, 1));
    assert!(summary.memory_bytes > 0);
    // 2.5 s: `used` gets a call every 250 ms, `streamed` has its (unread) stream open.
    for _ in 0..10 {
        tokio::time::sleep(Duration::from_millis(250)).await;
        client.describe_session(proto::DescribeSessionRequest { session_id: used.clone() }).await.unwrap();
    }
    let status = client.describe_session(proto::DescribeSessionRequest { session_id: abandoned.clone() }).await.unwrap_err();
    assert_eq!(status.code(), Code::NotFound, "the abandoned session was reaped");
    let listed = client.list_sessions(proto::ListSessionsRequest {}).await.unwrap().into_inner();
    let mut ids: Vec<_> = listed.sessions.iter().map(|s| s.session_id.clone()).collect();
    ids.sort();
    let mut expected = vec![streamed.clone(), used.clone()];
    expected.sort();
    assert_eq!(ids, expected);
    assert!(listed.sessions.iter().all(|s| s.idle_seconds < 1.0), "{:?}", listed.sessions);
    // The stream closed, its session's lease runs out too; the freed places are usable again.
    drop(stream);
    tokio::time::sleep(Duration::from_millis(2500)).await;
    let status = client.describe_session(proto::DescribeSessionRequest { session_id: streamed }).await.unwrap_err();
    assert_eq!(status.code(), Code::NotFound);
    assert!(client.list_sessions(proto::ListSessionsRequest {}).await.unwrap().into_inner().sessions.is_empty());
    still_serves(&mut client).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_connections_are_bounded_and_closed_while_live_clients_stay() {
    let server = start_server_with(Limits::default(), |_, options| {
        options.max_connections = 50;
        options.idle_connection_timeout = Duration::from_secs(1);
        options.keepalive_interval = Duration::from_millis(300);
        options.keepalive_timeout = Duration::from_secs(5);
    })
    .await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    still_serves(&mut client).await;
    // 1000 TCP connections that never speak: they used to stay open forever, and at the fd limit
    // the accept loop spun at 100 % of a core.
    let address = server.address.trim_start_matches("http://").to_string();
    let mut idle = Vec::new();
    for _ in 0..1000 {
        idle.push(tokio::net::TcpStream::connect(&address).await.unwrap());
    }
    // The live client keeps working; a new one is refused while the limit is reached.
    still_serves(&mut client).await;
    let refused = Channel::from_shared(server.address.clone()).unwrap().connect().await;
    if let Ok(channel) = refused {
        let status = RadServeClient::new(channel).list_sessions(proto::ListSessionsRequest {}).await.unwrap_err();
        // The connection was closed at once: tonic reports a transport error (grpcio: UNAVAILABLE).
        assert!(matches!(status.code(), Code::Unavailable | Code::Unknown | Code::Cancelled), "{status:?}");
        assert!(status.source().is_some(), "a transport failure, not an answer of the server: {status:?}");
    }
    // Past the idle timeout the silent ones are closed (the server's end reads as end-of-stream)...
    tokio::time::sleep(Duration::from_millis(2500)).await;
    use tokio::io::AsyncReadExt;
    let mut closed = 0;
    for stream in &mut idle {
        // Accepted ones got the server's HTTP/2 preface before it closed them: read past it.
        let mut bytes = [0u8; 256];
        let ended = tokio::time::timeout(Duration::from_millis(200), async {
            while let Ok(1..) = stream.read(&mut bytes).await {}
        });
        if ended.await.is_ok() {
            closed += 1;
        }
    }
    assert_eq!(closed, idle.len(), "every silent connection was closed");
    drop(idle);
    // ...while the live client, quiet as long, answered the keepalive pings and still works.
    still_serves(&mut client).await;
    let mut fresh = RadServeClient::new(connect(&server.address).await);
    still_serves(&mut fresh).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_allocation_is_charged_to_one_memory_budget() {
    let server = start_server(Limits { memory_bytes: 700 << 20, ..Limits::default() }).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    // 1024 dmc pixel envs were allowed at ~90 MiB each: here 16 are refused (before the simulators are
    // asked to build any: the_memory_budget_refuses_what_would_not_fit in radserve-core counts that).
    let request = proto::CreateSessionRequest { env_id: "dmc/cheetah-run".into(), num_envs: 16, ..Default::default() };
    let status = client.create_session(request).await.unwrap_err();
    // More than the whole budget: INVALID_ARGUMENT (no retry fits it); the second stream below
    // does not fit beside the first: RESOURCE_EXHAUSTED (it fits once the first ends).
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().starts_with("16 envs of dmc/cheetah-run (~96.5 MiB each) needs 1.51 GiB of memory"), "{}", status.message());
    assert!(status.message().contains("whole memory budget of 700.0 MiB"), "{}", status.message());
    // Streams that are never read: each holds (prefetch + 2) batches; the second no longer fits.
    let request = proto::CreateSessionRequest {
        env_id: "procgen/bigfish".into(),
        num_envs: 1,
        replay: replay_capacity(100),
        ..Default::default()
    };
    let session_id = client.create_session(request).await.unwrap().into_inner().session_id;
    client.reset(proto::ResetRequest { session_id: session_id.clone(), seed: Some(0), ..Default::default() }).await.unwrap();
    for _ in 0..20 {
        let actions = proto::Tensor { dtype: proto::DType::DtypeInt64 as i32, shape: vec![1], data: 0i64.to_le_bytes().to_vec().into() };
        client.step(proto::StepRequest { session_id: session_id.clone(), actions: Some(actions), ..Default::default() }).await.unwrap();
    }
    use proto::sample_batches_request::Augmentation;
    let translate = || proto::SampleBatchesRequest {
        session_id: session_id.clone(),
        batch_size: 16,
        augmentation: Some(Augmentation::PipelineText("translate(1000)".into())),
        ..Default::default()
    };
    let first = client.sample_batches(translate()).await.expect("one stream fits");
    let status = client.sample_batches(translate()).await.unwrap_err();
    assert_eq!(status.code(), Code::ResourceExhausted);
    assert!(status.message().starts_with("a sample stream of (prefetch 2 + 2) batches needs 366.2 MiB"), "{}", status.message());
    let (used, limit) = server.manager.memory();
    assert!(used > 366 << 20 && used <= limit, "{used} of {limit}");
    // The stream's memory comes back when it ends; the session's when it closes.
    drop(first);
    let deadline = Instant::now() + Duration::from_secs(10);
    let second = loop {
        match client.sample_batches(translate()).await {
            Ok(stream) => break stream,
            Err(status) if Instant::now() < deadline => {
                assert_eq!(status.code(), Code::ResourceExhausted);
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            Err(status) => panic!("the first stream's memory never came back: {status:?}"),
        }
    };
    drop(second);
    client.close_session(proto::CloseSessionRequest { session_id, discard_snapshot: false }).await.unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    while server.manager.memory().0 > 0 {
        assert!(Instant::now() < deadline, "{} bytes still reserved", server.manager.memory().0);
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_message_over_the_decoding_limit_is_refused_for_good_and_the_server_lives() {
    let server = start_server(Limits::default()).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let session_id = session_with_replay(&mut client).await;
    // One byte over what the server decodes: tonic's codec refuses it with OUT_OF_RANGE (not a code
    // that asks for a retry) before the message is read, naming the size and the limit.
    let actions = proto::Tensor {
        dtype: proto::DType::DtypeUint8 as i32,
        shape: vec![1],
        data: vec![0u8; radserve_service::MAX_MESSAGE_BYTES].into(),
    };
    let status = client.step(proto::StepRequest { session_id, actions: Some(actions), ..Default::default() }).await.unwrap_err();
    assert_eq!(status.code(), Code::OutOfRange, "{status:?}");
    assert!(status.message().contains(&radserve_service::MAX_MESSAGE_BYTES.to_string()), "{}", status.message());
    still_serves(&mut client).await;
}
