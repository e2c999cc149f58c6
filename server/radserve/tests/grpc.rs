//! The real server on 127.0.0.1:0, real worker processes, talked to over gRPC.

mod common;

use common::{connect, f32_tensor, start_server};
use radserve_service::proto::{self, rad_serve_client::RadServeClient};
use radserve_core::Limits;
use tokio_stream::StreamExt;
use tonic::Code;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serves_health_reflection_and_answers_bad_input() {
    let server = start_server(Limits { max_sessions: 2, ..Limits::default() }).await;
    let channel = connect(&server.address).await;

    // SERVING once the workers have listed their envs and the catalog is built (tens of seconds).
    let serving = tonic_health::pb::health_check_response::ServingStatus::Serving;
    let ready = common::wait_health(&channel, "radserve.v1.RadServe", serving, std::time::Duration::from_secs(300)).await;
    assert!(ready, "the server never reported SERVING");

    // Reflection answers in both versions, with the same services.
    macro_rules! list_services {
        ($version:ident) => {{
            use tonic_reflection::pb::$version::{
                server_reflection_client::ServerReflectionClient, server_reflection_request::MessageRequest,
                server_reflection_response::MessageResponse, ServerReflectionRequest,
            };
            let mut reflection = ServerReflectionClient::new(channel.clone());
            let request =
                ServerReflectionRequest { host: String::new(), message_request: Some(MessageRequest::ListServices(String::new())) };
            let mut replies = reflection.server_reflection_info(tokio_stream::iter(vec![request])).await.unwrap().into_inner();
            match replies.next().await.unwrap().unwrap().message_response {
                Some(MessageResponse::ListServicesResponse(list)) => list.service.into_iter().map(|s| s.name).collect::<Vec<_>>(),
                other => panic!("unexpected reflection answer {other:?}"),
            }
        }};
    }
    for services in [list_services!(v1), list_services!(v1alpha)] {
        assert!(services.contains(&"radserve.v1.RadServe".to_string()), "{services:?}");
        assert!(services.contains(&"grpc.health.v1.Health".to_string()), "{services:?}");
        assert!(services.contains(&"dm_env_rpc.v1.Environment".to_string()), "{services:?}");
    }

    let mut client = RadServeClient::new(channel);
    let info = client.server_info(proto::ServerInfoRequest {}).await.unwrap().into_inner();
    assert_eq!(info.version, env!("CARGO_PKG_VERSION"));
    assert_eq!(info.api, "radserve.v1");
    let unknown = client
        .create_session(proto::CreateSessionRequest { env_id: "gym/CartPol-v1".into(), num_envs: 1, ..Default::default() })
        .await
        .unwrap_err();
    assert_eq!(unknown.code(), Code::NotFound);
    assert!(unknown.message().contains("did you mean gym/CartPole-v1"), "{}", unknown.message());

    let session = client
        .create_session(proto::CreateSessionRequest { env_id: "gym/Pendulum-v1".into(), num_envs: 2, seed: 7, ..Default::default() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(session.frame_stack, 1);
    assert_eq!(session.autoreset_mode, "same-step");
    let session_id = session.session_id.clone();

    let step = |actions: proto::Tensor| proto::StepRequest { session_id: session_id.clone(), actions: Some(actions), ..Default::default() };
    let early = client.step(step(f32_tensor(&[2, 1], &[0.0, 0.0]))).await.unwrap_err();
    assert_eq!(early.code(), Code::FailedPrecondition);

    let reset = client.reset(proto::ResetRequest { session_id: session_id.clone(), seed: None, ..Default::default() }).await.unwrap().into_inner();
    let obs = reset.obs.unwrap();
    assert_eq!(obs.shape, vec![2, 3]);
    assert_eq!(obs.dtype, proto::DType::DtypeFloat32 as i32);
    assert_eq!(obs.data.len(), 2 * 3 * 4);

    let out_of_bounds = client.step(step(f32_tensor(&[2, 1], &[0.0, 2.5]))).await.unwrap_err();
    assert_eq!(out_of_bounds.code(), Code::InvalidArgument);
    assert!(out_of_bounds.message().contains("env 1, element 0 is outside [-2, 2]"), "{}", out_of_bounds.message());
    let mut lying = f32_tensor(&[2, 1], &[0.0, 0.0]);
    lying.dtype = 42;
    assert_eq!(client.step(step(lying)).await.unwrap_err().code(), Code::InvalidArgument);

    let stepped = client.step(step(f32_tensor(&[2, 1], &[1.0, -1.0]))).await.unwrap().into_inner();
    assert_eq!(stepped.reward.unwrap().data.len(), 2 * 8);
    assert_eq!(stepped.terminated.len(), 2);

    // The second session fits, the third does not: max_sessions is 2.
    let second = client
        .create_session(proto::CreateSessionRequest { env_id: "gym/CartPole-v1".into(), num_envs: 1, ..Default::default() })
        .await
        .unwrap();
    let third = client
        .create_session(proto::CreateSessionRequest { env_id: "gym/CartPole-v1".into(), num_envs: 1, ..Default::default() })
        .await
        .unwrap_err();
    assert_eq!(third.code(), Code::ResourceExhausted);
    client.close_session(proto::CloseSessionRequest { session_id: second.into_inner().session_id, discard_snapshot: false }).await.unwrap();

    let info = server.manager.describe(&radserve_core::Principal::local(), &session_id).await.unwrap();
    assert_eq!(info.total_env_steps, 2);

    server.stop.send(()).unwrap();
    server.task.await.unwrap().unwrap();
    // Shutting down closed every session.
    assert!(server.manager.describe(&radserve_core::Principal::local(), &session_id).await.is_err());
}
