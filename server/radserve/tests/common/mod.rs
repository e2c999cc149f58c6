//! The real server on 127.0.0.1:0 with real worker processes, shared by the integration tests.
#![allow(dead_code)] // each test binary uses its own part

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use radserve::ServerSettings;
use radserve_service::proto::{self, rad_serve_client::RadServeClient};
use radserve_core::{Limits, SessionManager};
use radserve_sim::GlBackend;
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use prost::bytes::{Buf, BufMut};
use tonic::transport::Channel;
use tonic::Status;

pub struct TestServer {
    pub address: String,
    pub manager: Arc<SessionManager>,
    pub stop: oneshot::Sender<()>,
    pub task: JoinHandle<anyhow::Result<()>>,
}

pub async fn start_server(limits: Limits) -> TestServer {
    start_server_with(limits, |_, _| {}).await
}

/// A server whose settings and serving options `adjust` changes first (worker timeouts, connection
/// limits...).
pub async fn start_server_with(limits: Limits, adjust: impl FnOnce(&mut ServerSettings, &mut radserve::ServeOptions)) -> TestServer {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = format!("http://{}", listener.local_addr().unwrap());
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut settings = ServerSettings {
        worker_program: PathBuf::from(env!("CARGO_BIN_EXE_radserve")),
        venv: repo.join(".venv"),
        gl: GlBackend::Egl,
        workers: 2,
        limits,
        worker_call_timeout: Duration::from_secs(60),
        worker_create_timeout: Duration::from_secs(300),
        acting: radserve_core::ActingConfig::default(),
        replay: radserve_core::ReplayConfig::default(),
    };
    let mut options = radserve::ServeOptions { augment_threads: 1, ..radserve::ServeOptions::default() };
    adjust(&mut settings, &mut options);
    let (manager, _workers) = radserve::session_manager(settings);
    let (stop, stopped) = oneshot::channel::<()>();
    let task = tokio::spawn(radserve::serve(listener, manager.clone(), options, async {
        let _ = stopped.await;
    }));
    TestServer { address, manager, stop, task }
}

/// The same server over the fake simulators (`radserve_core::fake`): the transport and the core
/// end to end, with faults injected, and no worker process.
pub async fn start_fake_server(limits: Limits, processes: usize) -> (TestServer, Arc<radserve_core::fake::FakeSimulators>) {
    start_fake_server_with(limits, processes, radserve::ServeOptions::default()).await
}

/// The fake server with serving options of the test's own (authentication, TLS).
pub async fn start_fake_server_with(
    limits: Limits,
    processes: usize,
    options: radserve::ServeOptions,
) -> (TestServer, Arc<radserve_core::fake::FakeSimulators>) {
    let simulators = radserve_core::fake::FakeSimulators::new(processes);
    (start_fake_server_on(simulators.clone(), limits, options).await, simulators)
}

/// The fake server over simulators the test prepared (faults injected before it starts).
pub async fn start_fake_server_on(
    simulators: Arc<radserve_core::fake::FakeSimulators>,
    limits: Limits,
    options: radserve::ServeOptions,
) -> TestServer {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = format!("http://{}", listener.local_addr().unwrap());
    let acting = radserve_core::ActingConfig {
        python: Some(repo_python()),
        program: Some(PathBuf::from(env!("CARGO_BIN_EXE_radserve"))),
        ..Default::default()
    };
    let manager = Arc::new(SessionManager::new(simulators.clone(), limits).with_acting(acting));
    let options = radserve::ServeOptions { augment_threads: 1, ..options };
    let (stop, stopped) = oneshot::channel::<()>();
    let task = tokio::spawn(radserve::serve(listener, manager.clone(), options, async {
        let _ = stopped.await;
    }));
    TestServer { address, manager, stop, task }
}

/// The repository's .venv Python (make setup), where the onnxruntime wheel is.
pub fn repo_python() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../.venv/bin/python")
}

/// Asks grpc.health.v1 about `service` until it answers `wanted` (true) or `timeout` passes (false).
pub async fn wait_health(channel: &Channel, service: &str, wanted: tonic_health::pb::health_check_response::ServingStatus,
                         timeout: std::time::Duration) -> bool {
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel.clone());
    let deadline = std::time::Instant::now() + timeout;
    while std::time::Instant::now() < deadline {
        let request = tonic_health::pb::HealthCheckRequest { service: service.into() };
        if health.check(request).await.is_ok_and(|answer| answer.into_inner().status == wanted as i32) {
            return true;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    false
}

pub async fn connect(address: &str) -> Channel {
    Channel::from_shared(address.to_string()).unwrap().connect().await.unwrap()
}

/// The server still creates, resets and closes a session.
pub async fn still_serves(client: &mut RadServeClient<Channel>) {
    let request = proto::CreateSessionRequest { env_id: "gym/CartPole-v1".into(), num_envs: 1, ..Default::default() };
    let session = client.create_session(request).await.expect("the server still serves").into_inner();
    client.reset(proto::ResetRequest { session_id: session.session_id.clone(), seed: Some(1), ..Default::default() }).await.unwrap();
    client.close_session(proto::CloseSessionRequest { session_id: session.session_id, discard_snapshot: false }).await.unwrap();
}

pub fn f32_tensor(shape: &[i64], values: &[f32]) -> proto::Tensor {
    proto::Tensor {
        dtype: proto::DType::DtypeFloat32 as i32,
        shape: shape.to_vec(),
        data: values.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>().into(),
    }
}


/// Any method's message as raw bytes, sent and received as they are (no protobuf on the client).
#[derive(Clone, Copy, Default)]
pub struct RawCodec;

impl Codec for RawCodec {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawCodec;
    type Decoder = RawCodec;

    fn encoder(&mut self) -> Self::Encoder {
        RawCodec
    }

    fn decoder(&mut self) -> Self::Decoder {
        RawCodec
    }
}

impl Encoder for RawCodec {
    type Item = Vec<u8>;
    type Error = Status;

    fn encode(&mut self, item: Vec<u8>, dst: &mut EncodeBuf<'_>) -> Result<(), Status> {
        dst.put_slice(&item);
        Ok(())
    }
}

impl Decoder for RawCodec {
    type Item = Vec<u8>;
    type Error = Status;

    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<Vec<u8>>, Status> {
        let bytes = src.copy_to_bytes(src.remaining());
        Ok(Some(bytes.to_vec()))
    }
}
