//! Fuzzing every RPC of the real server (real workers, small limits): sequences of requests with
//! arbitrary field values, and arbitrary bytes sent as any method's message. Every answer must be OK
//! or a status from the documented set (never INTERNAL, UNKNOWN or a dropped connection), the server
//! must keep serving, and once the sessions a case created are closed, the memory budget must be back
//! where it was (a refused request reserves nothing). Bounded in `cargo test` (PROPTEST_CASES,
//! default 48 sequences and 256 raw messages); `make fuzz` runs many more. Each property prints how
//! many cases it ran.
//! The same properties through grpcio, with hypothesis: tests/test_fuzz.py.

mod common;
// Field values and operations (proptest strategies).
#[path = "fuzz/strategies.rs"]
mod strategies;

use strategies::{op, ChannelUse, Op, PolicyModel, Target, POLICY_FIXTURES};

use std::collections::HashMap;
use std::future::Future;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::Duration;

use common::{connect, start_server_with, RawCodec, TestServer};
use proptest::prelude::*;
use proptest::test_runner::{TestCaseError, TestRunner};
use radserve_service::proto::{self, rad_serve_client::RadServeClient};
use radserve_core::Limits;
use tokio::runtime::Runtime;
use tokio_stream::StreamExt;
use tonic::transport::Channel;
use tonic::{Code, Status};

fn cases(default: u32) -> u32 {
    std::env::var("PROPTEST_CASES").ok().and_then(|value| value.parse().ok()).unwrap_or(default)
}

/// The statuses the API documents for a request the client got wrong or the server cannot take now.
const DOCUMENTED: &[Code] = &[
    Code::Ok,
    Code::InvalidArgument,
    Code::NotFound,
    // A session name its owner already uses.
    Code::AlreadyExists,
    Code::FailedPrecondition,
    Code::ResourceExhausted,
    Code::DeadlineExceeded,
    Code::Cancelled,
];

fn check(status: &Status, what: &str) -> Result<(), TestCaseError> {
    prop_assert!(DOCUMENTED.contains(&status.code()), "{what}: undocumented status {:?}: {}", status.code(), status.message());
    prop_assert!(status.message().len() <= 4096, "{what}: a {}-byte message", status.message().len());
    Ok(())
}

/// One server for every case of a test binary: starting workers per case would dominate the run.
struct Harness {
    runtime: Runtime,
    server: TestServer,
    channel: Channel,
    /// Sessions that live across cases: a CartPole with a filled replay buffer, a Pendulum, a rollout,
    /// a CartPole in EnvPool's asynchronous mode.
    base: Vec<String>,
    baseline_memory: u64,
}

fn harness() -> &'static Harness {
    static HARNESS: OnceLock<Harness> = OnceLock::new();
    HARNESS.get_or_init(|| {
        let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
        let limits = Limits {
            max_sessions: 8,
            max_envs_per_session: 8,
            max_total_envs: 24,
            replay_memory_bytes: 256 << 20,
            max_streams_per_session: 2,
            stream_memory_bytes: 64 << 20,
            session_idle_timeout_s: 0,
            unread_stream_timeout_s: 0,
            memory_bytes: 1 << 30,
        };
        let (server, channel, base) = runtime.block_on(async {
            // Named sessions are snapshotted (every 0.2 s) and restored: names repeat across cases
            // (in target/tmp, left for the next run to ignore: the harness lives as long as the process).
            let snapshots = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap().keep();
            let server = start_server_with(limits, |settings, _| {
                settings.replay = radserve_core::ReplayConfig {
                    snapshot_dir: Some(snapshots),
                    snapshot_interval_s: 0.2,
                    ..radserve_core::ReplayConfig::default()
                };
            })
            .await;
            let channel = connect(&server.address).await;
            let mut client = RadServeClient::new(channel.clone());
            // The catalog is built once, by a low-priority worker: on a loaded host that takes longer
            // than a case waits for an answer (60 s), so it is built before the cases.
            client.list_envs(proto::ListEnvsRequest::default()).await.unwrap();
            let mut base = Vec::new();
            for (env_id, replay) in [
                ("gym/CartPole-v1", Some(proto::ReplayOptions { capacity: 500, rollout_steps: 0 })),
                ("gym/Pendulum-v1", None),
                ("gym/Pendulum-v1", Some(proto::ReplayOptions { capacity: 0, rollout_steps: 8 })),
            ] {
                let request = proto::CreateSessionRequest { env_id: env_id.into(), num_envs: 2, replay, ..Default::default() };
                let id = client.create_session(request).await.unwrap().into_inner().session_id;
                client.reset(proto::ResetRequest { session_id: id.clone(), seed: Some(0), ..Default::default() }).await.unwrap();
                base.push(id);
            }
            // And one in EnvPool's asynchronous mode (3 envs, 2 a recv), async-reset.
            let options = HashMap::from([
                ("engine".to_string(), proto::OptionValue { value: Some(proto::option_value::Value::StringValue("envpool".into())) }),
                ("batch_size".to_string(), proto::OptionValue { value: Some(proto::option_value::Value::IntValue(2)) }),
            ]);
            let request = proto::CreateSessionRequest { env_id: "gym/CartPole-v1".into(), num_envs: 3, options, ..Default::default() };
            let id = client.create_session(request).await.unwrap().into_inner().session_id;
            client.async_reset(proto::AsyncResetRequest { session_id: id.clone(), seed: Some(0) }).await.unwrap();
            let async_base = id;
            let actions = [
                proto::Tensor { dtype: proto::DType::DtypeInt64 as i32, shape: vec![2], data: [0i64, 1].iter().flat_map(|a| a.to_le_bytes()).collect::<Vec<u8>>().into() },
                common::f32_tensor(&[2, 1], &[0.5, -0.5]),
                common::f32_tensor(&[2, 1], &[0.5, -0.5]),
            ];
            for _ in 0..40 {
                for (id, actions) in base.iter().zip(&actions) {
                    client.step(proto::StepRequest { session_id: id.clone(), actions: Some(actions.clone()), ..Default::default() }).await.unwrap();
                }
            }
            base.push(async_base);
            (server, channel, base)
        });
        let baseline_memory = server.manager.memory().0;
        Harness { runtime, server, channel, base, baseline_memory }
    })
}

// ---------------------------------------------------------------------------------------------
// Running a case.

/// Waits at most `limit` for `future`; `None` when it was still waiting (a stream that waits for
/// data that never comes is allowed to wait).
async fn within<T>(limit: Duration, future: impl Future<Output = T>) -> Option<T> {
    tokio::time::timeout(limit, future).await.ok()
}

/// Reads up to `count` messages of a response stream, waiting at most `wait` for each: the first
/// error status, if one comes (a stream that ends, or still waits for data, is fine).
async fn read_some<T>(mut stream: tonic::Streaming<T>, count: usize, wait: Duration) -> Result<(), Status> {
    for _ in 0..count {
        match within(wait, stream.next()).await {
            Some(Some(Ok(_))) => {}
            Some(Some(Err(status))) => return Err(status),
            Some(None) | None => break,
        }
    }
    Ok(())
}

struct Case {
    client: RadServeClient<Channel>,
    base: Vec<String>,
    created: Vec<String>,
    /// A shared-stepping channel was left unconnected: its memory returns after the server's connect timeout.
    unconnected_channel: bool,
}

/// Connects to a shared-stepping channel's socket as a same-host client would and sends `requests`; each
/// answer must be a documented status code with a well-formed length.
async fn use_channel(channel: &proto::SharedActingChannel, right_token: bool, requests: &[[u8; 16]]) -> Result<(), TestCaseError> {
    use std::os::linux::net::SocketAddrExt;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let address = std::os::unix::net::SocketAddr::from_abstract_name(channel.socket.as_bytes()).unwrap();
    let stream = std::os::unix::net::UnixStream::connect_addr(&address).map_err(|e| TestCaseError::fail(format!("connect: {e}")))?;
    stream.set_nonblocking(true).unwrap();
    let mut stream = tokio::net::UnixStream::from_std(stream).unwrap();
    let mut token = channel.token.to_vec();
    if !right_token {
        token[0] ^= 1;
    }
    if stream.write_all(&token).await.is_err() {
        return Ok(());
    }
    if right_token {
        // The memory's descriptor comes first, with one byte (read here without it: the kernel closes it).
        let mut handed = [0u8; 1];
        match within(Duration::from_secs(20), stream.read_exact(&mut handed)).await {
            Some(Ok(_)) => prop_assert_eq!(handed[0], 1),
            // Another connection of the case took the channel first.
            Some(Err(_)) | None => return Ok(()),
        }
    }
    for request in requests {
        if stream.write_all(request).await.is_err() {
            break;
        }
        let mut header = [0u8; 8];
        match within(Duration::from_secs(20), stream.read_exact(&mut header)).await {
            Some(Ok(_)) => {}
            // A wrong token: the server dropped the connection (or waits for the rightful client).
            Some(Err(_)) | None if !right_token => break,
            other => prop_assert!(false, "no answer on the shared-stepping channel: {other:?}"),
        }
        let code = Code::from_i32(u32::from_le_bytes(header[..4].try_into().unwrap()) as i32);
        let length = u32::from_le_bytes(header[4..].try_into().unwrap()) as usize;
        prop_assert!(DOCUMENTED.contains(&code), "shared-stepping channel answered {code:?}");
        prop_assert!(length <= 1 << 20, "an answer of {length} bytes");
        let mut body = vec![0u8; length];
        prop_assert!(stream.read_exact(&mut body).await.is_ok(), "a short answer");
    }
    Ok(())
}

impl Case {
    fn session(&self, target: &Target) -> String {
        match target {
            Target::Live(index) => {
                let live: Vec<&String> = self.base.iter().chain(&self.created).collect();
                live[index % live.len()].clone()
            }
            Target::Id(id) => id.clone(),
        }
    }

    /// Runs one call; a call the server does not answer within a minute fails the case (a freeze).
    async fn run(&mut self, op: Op) -> Result<(), TestCaseError> {
        let what = format!("{op:?}");
        let what: String = what.chars().take(300).collect();
        match tokio::time::timeout(Duration::from_secs(60), self.call(op)).await {
            Err(_) => Err(TestCaseError::fail(format!("no answer within 60 s: {what}"))),
            Ok(Err(failure)) => Err(failure),
            Ok(Ok(Err(status))) => check(&status, &what),
            Ok(Ok(Ok(()))) => Ok(()),
        }
    }

    async fn call(&mut self, op: Op) -> Result<Result<(), Status>, TestCaseError> {
        let limit = Duration::from_secs(20);
        Ok(match op {
            Op::ListEnvs(prefix) => self.client.list_envs(proto::ListEnvsRequest { prefix }).await.map(drop),
            Op::Create(request) => match self.client.create_session(request).await {
                Ok(info) => {
                    self.created.push(info.into_inner().session_id);
                    Ok(())
                }
                Err(status) => Err(status),
            },
            Op::Describe(target) => {
                self.client.describe_session(proto::DescribeSessionRequest { session_id: self.session(&target) }).await.map(drop)
            }
            Op::Close(target) => {
                let session_id = self.session(&target);
                if self.base.contains(&session_id) {
                    // The base sessions stay; closing another one (or a made-up id) is the case.
                    Ok(())
                } else {
                    let result = self.client.close_session(proto::CloseSessionRequest { session_id: session_id.clone(), discard_snapshot: false }).await;
                    if result.is_ok() {
                        self.created.retain(|id| *id != session_id);
                    }
                    result.map(drop)
                }
            }
            Op::ListSessions => self.client.list_sessions(proto::ListSessionsRequest {}).await.map(drop),
            Op::Reset(target, seed) => {
                let request = proto::ResetRequest { session_id: self.session(&target), seed, ..Default::default() };
                within(limit, self.client.reset(request)).await.expect("a reset answers").map(drop)
            }
            Op::Step(target, actions) => {
                let request = proto::StepRequest { session_id: self.session(&target), actions: Some(actions), ..Default::default() };
                within(limit, self.client.step(request)).await.expect("a step answers").map(drop)
            }
            Op::AsyncReset(target, seed) => {
                let request = proto::AsyncResetRequest { session_id: self.session(&target), seed };
                within(limit, self.client.async_reset(request)).await.expect("an async reset answers").map(drop)
            }
            Op::Send(target, actions, env_ids) => {
                let request = proto::SendRequest { session_id: self.session(&target), actions: Some(actions), env_ids };
                within(limit, self.client.send(request)).await.expect("a send answers").map(drop)
            }
            Op::Recv(target, send) => {
                let (actions, env_ids) = send.map_or((None, Vec::new()), |(actions, ids)| (Some(actions), ids));
                let request = proto::RecvRequest { session_id: self.session(&target), actions, env_ids };
                within(limit, self.client.recv(request)).await.expect("a recv answers").map(drop)
            }
            Op::Act(target, messages) => {
                let session_id = self.session(&target);
                let requests: Vec<proto::ActRequest> = messages
                    .into_iter()
                    .map(|message| proto::ActRequest {
                        request: message.map(|message| match message {
                            Ok(seed) => proto::act_request::Request::Reset(proto::ResetRequest { session_id: session_id.clone(), seed, ..Default::default() }),
                            Err(actions) => proto::act_request::Request::Step(proto::StepRequest {
                                session_id: session_id.clone(),
                                actions: Some(actions),
                                ..Default::default()
                            }),
                        }),
                    })
                    .collect();
                let expected = requests.len();
                match self.client.act(tokio_stream::iter(requests)).await {
                    Ok(response) => {
                        let mut stream = response.into_inner();
                        let mut outcome = Ok(());
                        for _ in 0..expected {
                            match within(limit, stream.next()).await.expect("an act stream answers") {
                                Some(Ok(_)) => {}
                                Some(Err(status)) => {
                                    outcome = Err(status);
                                    break;
                                }
                                None => break,
                            }
                        }
                        outcome
                    }
                    Err(status) => Err(status),
                }
            }
            Op::ShareActing(target, how) => {
                match self.client.share_acting(proto::ShareActingRequest { session_id: self.session(&target) }).await {
                    Ok(channel) => {
                        let channel = channel.into_inner();
                        match how {
                            ChannelUse::Leave => self.unconnected_channel = true,
                            ChannelUse::Connect { right_token, requests } => {
                                // A wrong token leaves the channel waiting for the rightful client.
                                self.unconnected_channel |= !right_token;
                                use_channel(&channel, right_token, &requests).await?
                            }
                        }
                        Ok(())
                    }
                    Err(status) => Err(status),
                }
            }
            Op::SetPolicy(target, model, head, version) => {
                let fixture = |index: usize| {
                    let name = POLICY_FIXTURES[index % POLICY_FIXTURES.len()];
                    std::fs::read(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../policy/tests/models").join(name)).unwrap()
                };
                let model = match model {
                    PolicyModel::Fixture(index) => fixture(index),
                    PolicyModel::Damaged(index, flips) => {
                        let mut bytes = fixture(index);
                        for (at, value) in flips {
                            let at = at % bytes.len();
                            bytes[at] = value;
                        }
                        bytes
                    }
                    PolicyModel::Bytes(bytes) => bytes,
                };
                let request = proto::SetPolicyRequest { session_id: self.session(&target), model, head, version, noise: None };
                within(limit, self.client.set_policy(request)).await.expect("a set_policy answers").map(drop)
            }
            Op::StartActing(target, mut request) => {
                request.session_id = self.session(&target);
                within(limit, self.client.start_acting(request)).await.expect("a start_acting answers").map(drop)
            }
            Op::StopActing(target) => {
                let request = proto::StopActingRequest { session_id: self.session(&target) };
                within(limit, self.client.stop_acting(request)).await.expect("a stop_acting answers").map(drop)
            }
            Op::UpdatePriorities(target, keys, priorities) => {
                let request = proto::UpdatePrioritiesRequest { session_id: self.session(&target), keys, priorities };
                within(limit, self.client.update_priorities(request)).await.expect("an update_priorities answers").map(drop)
            }
            Op::Sample(target, mut request) => {
                request.session_id = self.session(&target);
                // A few chunks, then the client leaves.
                match self.client.sample_batches(request).await {
                    Ok(response) => read_some(response.into_inner(), 6, Duration::from_millis(500)).await,
                    Err(status) => Err(status),
                }
            }
            Op::SampleShared(target, mut request, releases, release_first) => {
                request.session_id = self.session(&target);
                use proto::shared_sample_request::Request;
                let mut messages = Vec::new();
                if !release_first {
                    messages.push(proto::SharedSampleRequest { request: Some(Request::Start(request)) });
                }
                messages.extend(releases.into_iter().map(|slot| proto::SharedSampleRequest { request: Some(Request::Release(slot)) }));
                // The client keeps its side open briefly, as a real one would while it reads.
                let (sender, receiver) = tokio::sync::mpsc::channel(8);
                for message in messages {
                    sender.send(message).await.unwrap();
                }
                // Only releases: the client closes its side after them (a client that stays silent
                // is a test of its own in hardening.rs).
                let sender = (!release_first).then_some(sender);
                let requests = tokio_stream::wrappers::ReceiverStream::new(receiver);
                let outcome = match self.client.sample_batches_shared(requests).await {
                    Ok(response) => read_some(response.into_inner(), 3, Duration::from_millis(500)).await,
                    Err(status) => Err(status),
                };
                drop(sender);
                outcome
            }
        })
    }

    /// Closes what the case created, checks the server still serves, and waits for every
    /// reservation of the case (sessions, streams, channels) to be returned.
    async fn finish(mut self, baseline: u64, manager: &radserve_core::SessionManager) -> Result<(), TestCaseError> {
        for session_id in std::mem::take(&mut self.created) {
            let result = self.client.close_session(proto::CloseSessionRequest { session_id, discard_snapshot: false }).await;
            if let Err(status) = result {
                check(&status, "closing a created session")?;
            }
        }
        for session_id in &self.base {
            // The base sessions outlive the case: an actor the case started on one stops here.
            let stopped = self.client.stop_acting(proto::StopActingRequest { session_id: session_id.clone() }).await;
            prop_assert!(stopped.is_ok(), "stopping a base session's actor: {stopped:?}");
            let info = self.client.describe_session(proto::DescribeSessionRequest { session_id: session_id.clone() }).await;
            prop_assert!(info.is_ok(), "a base session is gone: {info:?}");
        }
        let listed = self.client.list_envs(proto::ListEnvsRequest { prefix: "gym/CartPole".into() }).await;
        prop_assert!(listed.is_ok(), "ListEnvs failed after the case: {listed:?}");
        let mut used = manager.memory().0;
        let wait = if self.unconnected_channel { radserve_service::shared_stepping::CONNECT_TIMEOUT + Duration::from_secs(3) } else { Duration::from_secs(5) };
        for _ in 0..wait.as_millis() / 50 {
            if used == baseline {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
            used = manager.memory().0;
        }
        prop_assert_eq!(used, baseline, "memory still reserved after the case's sessions and streams ended");
        prop_assert_eq!(manager.list_sessions(&radserve_core::Principal::local()).len(), self.base.len());
        Ok(())
    }
}

/// The properties share one server and check its memory between cases: one runs at a time.
fn serial() -> std::sync::MutexGuard<'static, ()> {
    static SERIAL: Mutex<()> = Mutex::new(());
    SERIAL.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

fn runner(default_cases: u32) -> TestRunner {
    TestRunner::new(ProptestConfig {
        cases: cases(default_cases),
        max_shrink_iters: 64,
        // A case that freezes takes a minute to fail; shrinking stops after two.
        max_shrink_time: 120_000,
        // The failing case is printed; these runners have no source file to store it next to.
        failure_persistence: None,
        ..ProptestConfig::default()
    })
}

/// After a property: the server still creates, resets and closes a session, and its task is alive.
fn still_serves(harness: &Harness) {
    harness.runtime.block_on(common::still_serves(&mut RadServeClient::new(harness.channel.clone())));
    assert!(!harness.server.task.is_finished());
}

#[test]
fn request_sequences_get_documented_answers_and_reserve_nothing_once_closed() {
    let _serial = serial();
    let harness = harness();
    let executed = AtomicUsize::new(0);
    let result = runner(48).run(&prop::collection::vec(op(), 1..8), |ops| {
        executed.fetch_add(1, Ordering::Relaxed);
        harness.runtime.block_on(async {
            let mut case = Case {
                client: RadServeClient::new(harness.channel.clone()),
                base: harness.base.clone(),
                created: Vec::new(),
                unconnected_channel: false,
            };
            for op in ops {
                case.run(op).await?;
            }
            match tokio::time::timeout(Duration::from_secs(60), case.finish(harness.baseline_memory, &harness.server.manager)).await {
                Ok(result) => result,
                Err(_) => Err(TestCaseError::fail("closing the case's sessions took over 60 s")),
            }
        })
    });
    if let Err(error) = result {
        panic!("{error}");
    }
    still_serves(harness);
    eprintln!("fuzz: {} request sequences (with shrinking), none crashed the server", executed.into_inner());
}

// ---------------------------------------------------------------------------------------------
// Arbitrary bytes as any method's message, through a codec that sends them as they are.

const METHODS: &[(&str, bool, bool)] = &[
    // (method, client streams, server streams)
    ("ServerInfo", false, false),
    ("ListEnvs", false, false),
    ("CreateSession", false, false),
    ("DescribeSession", false, false),
    ("CloseSession", false, false),
    ("ListSessions", false, false),
    ("Reset", false, false),
    ("Step", false, false),
    ("Act", true, true),
    ("AsyncReset", false, false),
    ("Send", false, false),
    ("Recv", false, false),
    ("ShareActing", false, false),
    ("SampleBatches", false, true),
    ("SampleBatchesShared", true, true),
    ("SetPolicy", false, false),
    ("StartActing", false, false),
    ("StopActing", false, false),
    ("UpdatePriorities", false, false),
    // dm_env_rpc on the same port (a full path: another service).
    ("/dm_env_rpc.v1.Environment/Process", true, true),
];

/// Anything at all, or a live session's id as field 1 (every session-scoped request's `session_id`)
/// followed by a field of any number and wire type with any payload, so that the decoder and the
/// handlers behind it both get exercised. CloseSession never names a base session.
fn raw_message(base: Vec<String>) -> impl Strategy<Value = (usize, Vec<u8>)> {
    let garbage = prop::collection::vec(any::<u8>(), 0..64);
    let structured = (0..METHODS.len(), any::<usize>(), 1u8..20, 0u8..8, prop::collection::vec(any::<u8>(), 0..24), any::<bool>())
        .prop_map(move |(method, session, field, wire_type, payload, with_session)| {
            let mut bytes = Vec::new();
            if with_session && METHODS[method].0 != "CloseSession" {
                let id = base[session % base.len()].as_bytes();
                bytes.push(0x0a); // field 1, length-delimited
                bytes.push(id.len() as u8);
                bytes.extend_from_slice(id);
            }
            bytes.push((field << 3) | wire_type);
            bytes.extend_from_slice(&payload);
            (method, bytes)
        });
    prop_oneof![(0..METHODS.len(), garbage), structured]
}

#[test]
fn arbitrary_bytes_as_any_message_get_documented_answers() {
    let _serial = serial();
    let harness = harness();
    let executed = AtomicUsize::new(0);
    let result = runner(256).run(&raw_message(harness.base.clone()), |(method, body)| {
        executed.fetch_add(1, Ordering::Relaxed);
        harness.runtime.block_on(async {
            let (name, client_streams, server_streams) = METHODS[method];
            let path = if name.starts_with('/') { name.to_string() } else { format!("/radserve.v1.RadServe/{name}") };
            let path: tonic::codegen::http::uri::PathAndQuery = path.parse().unwrap();
            let mut grpc = tonic::client::Grpc::new(harness.channel.clone());
            grpc.ready().await.map_err(|error| TestCaseError::fail(format!("the server stopped accepting calls: {error}")))?;
            let outcome: Result<(), Status> = match (client_streams, server_streams) {
                (false, false) => grpc.unary(tonic::Request::new(body), path, RawCodec).await.map(drop),
                (false, true) => match grpc.server_streaming(tonic::Request::new(body), path, RawCodec).await {
                    Ok(response) => read_some(response.into_inner(), 1, Duration::from_millis(300)).await,
                    Err(status) => Err(status),
                },
                (true, _) => {
                    let requests = tokio_stream::iter(vec![body.clone(), body]);
                    match grpc.streaming(tonic::Request::new(requests), path, RawCodec).await {
                        Ok(response) => read_some(response.into_inner(), 1, Duration::from_millis(300)).await,
                        Err(status) => Err(status),
                    }
                }
            };
            if let Err(status) = outcome {
                check(&status, &format!("raw {name}"))?;
            }
            let mut client = RadServeClient::new(harness.channel.clone());
            let listed = client.list_sessions(proto::ListSessionsRequest {}).await;
            prop_assert!(listed.is_ok(), "the server still answers: {listed:?}");
            // A raw CreateSession that decodes creates a session like any other: close it.
            for summary in listed.unwrap().into_inner().sessions {
                if !harness.base.contains(&summary.session_id) {
                    client.close_session(proto::CloseSessionRequest { session_id: summary.session_id, discard_snapshot: false }).await.unwrap();
                }
            }
            Ok(())
        })
    });
    if let Err(error) = result {
        panic!("{error}");
    }
    // A raw ShareActing that named a base session left a channel no client takes: the server drops it
    // after its connect timeout, and then holds nothing the messages caused.
    harness.runtime.block_on(async {
        let deadline = tokio::time::Instant::now() + radserve_service::shared_stepping::CONNECT_TIMEOUT + Duration::from_secs(3);
        while harness.server.manager.memory().0 != harness.baseline_memory && tokio::time::Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    });
    assert_eq!(harness.server.manager.memory().0, harness.baseline_memory, "memory still reserved after the raw messages");
    still_serves(harness);
    eprintln!("fuzz: {} raw messages (with shrinking), none crashed the server", executed.into_inner());
}

