//! The Prometheus endpoint over the fake simulators: what the sessions did shows in the counters,
//! gauges and the step-latency histogram, and the HTTP endpoint answers GET /metrics (and nothing
//! else). A real server's endpoint, scraped and parsed by Prometheus' own Python parser, is
//! tests/test_metrics.py.

mod common;

use std::collections::HashMap;

use common::{connect, start_fake_server};
use radserve::metrics::{render, Sources};
use radserve_core::fake::FAKE_ENV;
use radserve_core::Limits;
use radserve_service::proto::{self, rad_serve_client::RadServeClient};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_stream::StreamExt;

/// `name{labels} value` lines of the exposition (comments left out).
fn samples(text: &str) -> HashMap<String, f64> {
    text.lines()
        .filter(|line| !line.starts_with('#') && !line.is_empty())
        .map(|line| {
            let (name, value) = line.rsplit_once(' ').unwrap_or_else(|| panic!("no value in {line:?}"));
            (name.to_string(), value.parse().unwrap_or_else(|_| panic!("not a number in {line:?}")))
        })
        .collect()
}

async fn get(address: std::net::SocketAddr, request: &str) -> String {
    let mut stream = tokio::net::TcpStream::connect(address).await.unwrap();
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut answer = String::new();
    stream.read_to_string(&mut answer).await.unwrap();
    answer
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_show_what_the_sessions_did() {
    let (server, _simulators) = start_fake_server(Limits::default(), 2).await;
    let sources = Sources { manager: server.manager.clone(), workers: None };
    let before = samples(&render(&sources).unwrap());
    assert_eq!(before["radserve_env_steps_total{family=\"gym\"}"], 0.0);
    assert_eq!(before["radserve_sessions"], 0.0);

    let mut client = RadServeClient::new(connect(&server.address).await);
    let session = client
        .create_session(proto::CreateSessionRequest {
            env_id: FAKE_ENV.into(),
            num_envs: 3,
            replay: Some(proto::ReplayOptions { capacity: 100, ..Default::default() }),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner()
        .session_id;
    client.reset(proto::ResetRequest { session_id: session.clone(), seed: Some(1), ..Default::default() }).await.unwrap();
    let actions = proto::Tensor { dtype: proto::DType::DtypeInt64 as i32, shape: vec![3], data: vec![0u8; 24].into() };
    let mut episodes = 0;
    for _ in 0..10 {
        let step = proto::StepRequest { session_id: session.clone(), actions: Some(actions.clone()), ..Default::default() };
        episodes += client.step(step).await.unwrap().into_inner().episodes.len();
    }
    let request = proto::SampleBatchesRequest { session_id: session.clone(), batch_size: 4, max_batches: Some(2), ..Default::default() };
    let mut stream = client.sample_batches(request).await.unwrap().into_inner();
    while stream.next().await.transpose().unwrap().is_some() {}

    let after = samples(&render(&sources).unwrap());
    assert_eq!(after["radserve_env_steps_total{family=\"gym\"}"], 30.0);
    assert_eq!(after["radserve_env_steps_total{family=\"dmc\"}"], 0.0);
    assert_eq!(after["radserve_episodes_total"], episodes as f64);
    assert!(episodes > 0);
    assert_eq!(after["radserve_resets_total"], 1.0);
    assert_eq!(after["radserve_batches_total"], 2.0);
    assert_eq!(after["radserve_step_seconds_count"], 10.0);
    assert_eq!(after["radserve_step_seconds_bucket{le=\"+Inf\"}"], 10.0);
    assert!(after["radserve_step_seconds_sum"] > 0.0);
    assert_eq!(after["radserve_sessions"], 1.0);
    assert_eq!(after["radserve_envs{family=\"gym\"}"], 3.0);
    assert_eq!(after["radserve_replay_transitions"], 30.0);
    assert!(after["radserve_replay_bytes"] > 0.0);
    assert!(after["radserve_memory_used_bytes"] > 0.0 && after["radserve_memory_used_bytes"] <= after["radserve_memory_budget_bytes"]);

    // Counters stay when the session goes; its gauges do not.
    client.close_session(proto::CloseSessionRequest { session_id: session, discard_snapshot: false }).await.unwrap();
    let closed = samples(&render(&sources).unwrap());
    assert_eq!(closed["radserve_env_steps_total{family=\"gym\"}"], 30.0);
    assert_eq!((closed["radserve_sessions"], closed["radserve_envs{family=\"gym\"}"], closed["radserve_replay_transitions"]), (0.0, 0.0, 0.0));

    // Over HTTP: GET /metrics in the OpenMetrics format; anything else a clear refusal.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap();
    tokio::spawn(radserve::metrics::serve(listener, sources));
    let answer = get(address, "GET /metrics HTTP/1.1\r\nHost: radserve\r\nConnection: close\r\n\r\n").await;
    assert!(answer.starts_with("HTTP/1.1 200 OK\r\n"), "{answer}");
    assert!(answer.contains("content-type: application/openmetrics-text; version=1.0.0"), "{answer}");
    assert!(answer.contains("radserve_env_steps_total{family=\"gym\"} 30\n") && answer.trim_end().ends_with("# EOF"), "{answer}");
    let elsewhere = get(address, "GET / HTTP/1.1\r\nHost: radserve\r\nConnection: close\r\n\r\n").await;
    assert!(elsewhere.starts_with("HTTP/1.1 404"), "{elsewhere}");
    let posted = get(address, "POST /metrics HTTP/1.1\r\nHost: radserve\r\nContent-Length: 0\r\nConnection: close\r\n\r\n").await;
    assert!(posted.starts_with("HTTP/1.1 405"), "{posted}");
}
