//! Authentication and ownership over every RPC of the service, table-driven: the table must name
//! every method the proto declares (read from the descriptor set the server serves), so an RPC
//! added without a row fails here before it can ship unchecked. Each method is called with no
//! token, a wrong token, a monitor's token, another principal's token on a session it does not
//! own, and the owner's token. Over the fake simulators; TLS and the Python client are
//! tests/test_security.py.

#![allow(clippy::wildcard_enum_match_arm, reason = "a test's match names what it expects; anything else fails the test")]

mod common;

use std::collections::{BTreeSet, HashMap};
use std::time::Duration;

use common::{connect, start_fake_server_with, RawCodec};
use prost::Message;
use radserve_core::fake::FAKE_ENV;
use radserve_core::{Limits, Principal, PrincipalLimits, Role};
use radserve_service::auth::{digest, AuthPolicy};
use radserve_service::proto;
use tokio_stream::StreamExt;
use tonic::transport::Channel;
use tonic::{Code, Status};

const ALICE: &str = "alice-token";
const BOB: &str = "bob-token";
const GRAFANA: &str = "grafana-token";

/// What a method acts on.
#[derive(Clone, Copy, PartialEq)]
enum Scope {
    /// The server (no session in the request).
    Server,
    /// The session in the request.
    Session,
}

struct Row {
    method: &'static str,
    client_streams: bool,
    server_streams: bool,
    scope: Scope,
    /// The request (for a client stream: its first message) for a session id.
    request: fn(&str) -> Vec<u8>,
}

fn sample(session_id: &str) -> proto::SampleBatchesRequest {
    proto::SampleBatchesRequest { session_id: session_id.into(), batch_size: 2, ..Default::default() }
}

const TABLE: &[Row] = &[
    Row { method: "ServerInfo", client_streams: false, server_streams: false, scope: Scope::Server, request: |_| {
        proto::ServerInfoRequest::default().encode_to_vec()
    } },
    Row { method: "ListEnvs", client_streams: false, server_streams: false, scope: Scope::Server, request: |_| {
        proto::ListEnvsRequest::default().encode_to_vec()
    } },
    Row { method: "CreateSession", client_streams: false, server_streams: false, scope: Scope::Server, request: |_| {
        proto::CreateSessionRequest { env_id: FAKE_ENV.into(), num_envs: 1, ..Default::default() }.encode_to_vec()
    } },
    Row { method: "ListSessions", client_streams: false, server_streams: false, scope: Scope::Server, request: |_| {
        proto::ListSessionsRequest::default().encode_to_vec()
    } },
    Row { method: "DescribeSession", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        proto::DescribeSessionRequest { session_id: id.into() }.encode_to_vec()
    } },
    Row { method: "CloseSession", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        proto::CloseSessionRequest { session_id: id.into(), discard_snapshot: false }.encode_to_vec()
    } },
    Row { method: "Reset", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        proto::ResetRequest { session_id: id.into(), seed: Some(1), ..Default::default() }.encode_to_vec()
    } },
    Row { method: "Step", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        let actions = proto::Tensor { dtype: proto::DType::DtypeInt64 as i32, shape: vec![2], data: vec![0u8; 16].into() };
        proto::StepRequest { session_id: id.into(), actions: Some(actions), ..Default::default() }.encode_to_vec()
    } },
    Row { method: "Act", client_streams: true, server_streams: true, scope: Scope::Session, request: |id| {
        let reset = proto::ResetRequest { session_id: id.into(), seed: Some(1), ..Default::default() };
        proto::ActRequest { request: Some(proto::act_request::Request::Reset(reset)) }.encode_to_vec()
    } },
    Row { method: "AsyncReset", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        proto::AsyncResetRequest { session_id: id.into(), seed: Some(1) }.encode_to_vec()
    } },
    Row { method: "Send", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        let actions = proto::Tensor { dtype: proto::DType::DtypeInt64 as i32, shape: vec![1], data: vec![0u8; 8].into() };
        proto::SendRequest { session_id: id.into(), actions: Some(actions), env_ids: vec![0] }.encode_to_vec()
    } },
    Row { method: "Recv", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        proto::RecvRequest { session_id: id.into(), ..Default::default() }.encode_to_vec()
    } },
    Row { method: "ShareActing", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        proto::ShareActingRequest { session_id: id.into() }.encode_to_vec()
    } },
    Row { method: "SampleBatches", client_streams: false, server_streams: true, scope: Scope::Session, request: |id| {
        sample(id).encode_to_vec()
    } },
    Row { method: "SampleBatchesShared", client_streams: true, server_streams: true, scope: Scope::Session, request: |id| {
        proto::SharedSampleRequest { request: Some(proto::shared_sample_request::Request::Start(sample(id))) }.encode_to_vec()
    } },
    Row { method: "SetPolicy", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        let model = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/../policy/tests/models/categorical_fake.onnx")).unwrap();
        proto::SetPolicyRequest { session_id: id.into(), model, head: proto::PolicyHead::Categorical as i32, version: 1, noise: None }
            .encode_to_vec()
    } },
    Row { method: "StartActing", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        proto::StartActingRequest { session_id: id.into(), ..Default::default() }.encode_to_vec()
    } },
    Row { method: "StopActing", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        proto::StopActingRequest { session_id: id.into() }.encode_to_vec()
    } },
    Row { method: "UpdatePriorities", client_streams: false, server_streams: false, scope: Scope::Session, request: |id| {
        proto::UpdatePrioritiesRequest { session_id: id.into(), keys: vec![], priorities: vec![] }.encode_to_vec()
    } },
];

/// Calls `method` with `body` and `token`; a stream that opens and sends nothing wrong within a
/// moment counts as accepted.
async fn call(channel: &Channel, row: &Row, body: Vec<u8>, token: Option<&str>) -> Result<(), Status> {
    let path: tonic::codegen::http::uri::PathAndQuery = format!("/radserve.v1.RadServe/{}", row.method).parse().unwrap();
    let mut grpc = tonic::client::Grpc::new(channel.clone());
    grpc.ready().await.unwrap();
    let first = |stream: tonic::Streaming<Vec<u8>>| async move {
        let mut stream = stream;
        match tokio::time::timeout(Duration::from_millis(300), stream.next()).await {
            Ok(Some(Err(status))) => Err(status),
            Ok(Some(Ok(_)) | None) | Err(_) => Ok(()),
        }
    };
    match (row.client_streams, row.server_streams) {
        (false, false) => grpc.unary(authorized(body, token), path, RawCodec).await.map(drop),
        (false, true) => first(grpc.server_streaming(authorized(body, token), path, RawCodec).await?.into_inner()).await,
        (true, _) => {
            // The stream stays open after its first message, as a client's does.
            let requests = tokio_stream::iter(vec![body]).chain(tokio_stream::pending());
            first(grpc.streaming(authorized(requests, token), path, RawCodec).await?.into_inner()).await
        }
    }
}

fn authorized<T>(message: T, token: Option<&str>) -> tonic::Request<T> {
    let mut request = tonic::Request::new(message);
    if let Some(token) = token {
        request.metadata_mut().insert("authorization", format!("Bearer {token}").parse().unwrap());
    }
    request
}

fn principal(name: &str, role: Role) -> Principal {
    Principal::new(name, role, PrincipalLimits::default())
}

/// Every method of the RadServe service, as the server's descriptor set declares them.
fn declared_methods() -> BTreeSet<String> {
    let set = prost_types::FileDescriptorSet::decode(radserve_service::proto::FILE_DESCRIPTOR_SET).unwrap();
    set.file
        .iter()
        .flat_map(|file| &file.service)
        .filter(|service| service.name() == "RadServe")
        .flat_map(|service| service.method.iter().map(|method| method.name().to_string()))
        .collect()
}

async fn new_session(channel: &Channel, token: &str) -> String {
    let mut client = proto::rad_serve_client::RadServeClient::new(channel.clone());
    let request = proto::CreateSessionRequest {
        env_id: FAKE_ENV.into(),
        num_envs: 2,
        replay: Some(proto::ReplayOptions { capacity: 100, ..Default::default() }),
        ..Default::default()
    };
    client.create_session(authorized(request, Some(token))).await.unwrap().into_inner().session_id
}

/// A fake server that admits alice and bob (users) and grafana (monitor) by their tokens.
async fn server_with_tokens() -> (common::TestServer, std::sync::Arc<radserve_core::fake::FakeSimulators>) {
    let mut tokens = HashMap::new();
    tokens.insert(digest(ALICE.as_bytes()), principal("alice", Role::User));
    tokens.insert(digest(BOB.as_bytes()), principal("bob", Role::User));
    tokens.insert(digest(GRAFANA.as_bytes()), principal("grafana", Role::Monitor));
    let options = radserve::ServeOptions {
        security: radserve::Security { auth: AuthPolicy::tokens(tokens, false), ..Default::default() },
        ..Default::default()
    };
    start_fake_server_with(Limits::default(), 1, options).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_rpc_checks_the_token_the_role_and_the_owner() {
    let listed: BTreeSet<String> = TABLE.iter().map(|row| row.method.to_string()).collect();
    assert_eq!(listed, declared_methods(), "every RPC needs a row in this table (and so its checks)");

    let (server, _simulators) = server_with_tokens().await;
    let channel = connect(&server.address).await;
    let never_created = "s999-0123456789abcdef";

    for row in TABLE {
        let method = row.method;
        let session = new_session(&channel, ALICE).await;
        let body = (row.request)(&session);
        let code = |result: Result<(), Status>| result.err().map_or(Code::Ok, |status| status.code());

        assert_eq!(code(call(&channel, row, body.clone(), None).await), Code::Unauthenticated, "{method} without a token");
        assert_eq!(code(call(&channel, row, body.clone(), Some("bob-tokem")).await), Code::Unauthenticated, "{method}, wrong token");

        let monitored = code(call(&channel, row, body.clone(), Some(GRAFANA)).await);
        if radserve_service::auth::MONITOR_METHODS.contains(&method) {
            assert_eq!(monitored, Code::Ok, "{method} is open to monitors");
        } else {
            assert_eq!(monitored, Code::PermissionDenied, "{method} by a monitor");
        }

        let by_bob = call(&channel, row, body.clone(), Some(BOB)).await;
        match row.scope {
            Scope::Session => {
                // Not found, worded exactly as for a session that never existed.
                let status = by_bob.expect_err(method);
                let unknown = call(&channel, row, (row.request)(never_created), Some(BOB)).await.expect_err(method);
                assert_eq!(status.code(), Code::NotFound, "{method} on another principal's session: {status:?}");
                assert_eq!(status.message().replace(&session, "ID"), unknown.message().replace(never_created, "ID"), "{method}");
            }
            Scope::Server => assert_eq!(code(by_bob), Code::Ok, "{method} by any user"),
        }

        let by_alice = code(call(&channel, row, body, Some(ALICE)).await);
        assert!(
            !matches!(by_alice, Code::Unauthenticated | Code::PermissionDenied | Code::NotFound),
            "{method} by the owner: {by_alice:?}"
        );
    }

    // Health answers without a token; reflection does not (auth.open_reflection is off).
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel.clone());
    let status = health.check(tonic_health::pb::HealthCheckRequest::default()).await.unwrap().into_inner().status;
    assert_eq!(status, tonic_health::pb::health_check_response::ServingStatus::Serving as i32);
    let mut reflection =
        tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient::new(channel.clone());
    let request = tonic_reflection::pb::v1::ServerReflectionRequest {
        message_request: Some(tonic_reflection::pb::v1::server_reflection_request::MessageRequest::ListServices(String::new())),
        ..Default::default()
    };
    let refused = reflection.server_reflection_info(tokio_stream::iter(vec![request])).await;
    assert_eq!(refused.err().map(|status| status.code()), Some(Code::Unauthenticated));
}

/// Every service the descriptor set declares: a new one fails here until this file checks it.
#[test]
fn every_served_service_is_checked_here() {
    let set = prost_types::FileDescriptorSet::decode(radserve_service::proto::FILE_DESCRIPTOR_SET).unwrap();
    let services: BTreeSet<String> = set
        .file
        .iter()
        .flat_map(|file| file.service.iter().map(move |service| format!("{}.{}", file.package(), service.name())))
        .collect();
    let checked: BTreeSet<String> = ["radserve.v1.RadServe", "dm_env_rpc.v1.Environment"].map(String::from).into();
    assert_eq!(services, checked);
}

/// dm_env_rpc's one method: behind the same token check (a stream refused at once), closed to
/// monitors, and a world of another principal is unknown, in-band, in the words a world never
/// created gets.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dm_env_rpc_checks_the_token_the_role_and_the_owner() {
    use radserve_service::pb::dm_env_rpc::v1 as dm;
    use dm::environment_request::Payload as In;
    use dm::environment_response::Payload as Out;

    let (server, _simulators) = server_with_tokens().await;
    let channel = connect(&server.address).await;
    // One request, its answer (or the stream's status).
    let send = |token: Option<&'static str>, request: In| {
        let channel = channel.clone();
        async move {
            let mut client = dm::environment_client::EnvironmentClient::new(channel);
            let requests = tokio_stream::iter(vec![dm::EnvironmentRequest { payload: Some(request) }]).chain(tokio_stream::pending());
            let mut replies = client.process(authorized(requests, token)).await?.into_inner();
            replies.next().await.expect("an answer").map(|reply| reply.payload.expect("a payload"))
        }
    };
    let create = || {
        let env_id = dm::Tensor {
            payload: Some(dm::tensor::Payload::Strings(dm::tensor::StringArray { array: vec![FAKE_ENV.into()] })),
            shape: vec![],
        };
        In::CreateWorld(dm::CreateWorldRequest { settings: HashMap::from([("env_id".to_string(), env_id)]) })
    };
    for token in [None, Some("bob-tokem")] {
        assert_eq!(send(token, create()).await.unwrap_err().code(), Code::Unauthenticated);
    }
    assert_eq!(send(Some(GRAFANA), create()).await.unwrap_err().code(), Code::PermissionDenied);
    let world = match send(Some(ALICE), create()).await.unwrap() {
        Out::CreateWorld(created) => created.world_name,
        other => panic!("{other:?}"),
    };
    let join = |world: &str| In::JoinWorld(dm::JoinWorldRequest { world_name: world.into(), settings: HashMap::new() });
    let refusal = |answer: Result<Out, Status>| match answer.unwrap() {
        Out::Error(status) => status,
        other => panic!("expected an in-band error, got {other:?}"),
    };
    let never_created = "s999-0123456789abcdef";
    let by_bob = refusal(send(Some(BOB), join(&world)).await);
    let unknown = refusal(send(Some(BOB), join(never_created)).await);
    assert_eq!(by_bob.code, Code::NotFound as i32);
    assert_eq!(by_bob.message.replace(&world, "ID"), unknown.message.replace(never_created, "ID"));
    let destroy = |world: &str| In::DestroyWorld(dm::DestroyWorldRequest { world_name: world.into() });
    assert_eq!(refusal(send(Some(BOB), destroy(&world)).await).code, Code::NotFound as i32);
    assert!(matches!(send(Some(ALICE), destroy(&world)).await.unwrap(), Out::DestroyWorld(_)));
}
