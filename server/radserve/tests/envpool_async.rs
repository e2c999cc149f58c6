//! EnvPool's asynchronous mode through the real worker processes: a session built with option
//! `batch_size` below its envs (engine "envpool"), async-reset, then stepped by recv/send of half of
//! its envs at a time, end to end from the core's session through the worker protocol to EnvPool's
//! threads. The catalog does not offer the option to clients yet, so the session is built here
//! directly on the server's worker pool.

use std::path::PathBuf;
use std::time::Duration;

use radserve::ServerSettings;
use radserve_core::catalog::{resolve_options, BATCH_SIZE, FRAME_STACK};
use radserve_core::session::{Session, SessionConfig};
use radserve_core::{DType, EnvId, Family, Limits, OptionValue, Options};
use radserve_sim::GlBackend;

fn settings() -> ServerSettings {
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    ServerSettings {
        worker_program: PathBuf::from(env!("CARGO_BIN_EXE_radserve")),
        venv: repo.join(".venv"),
        gl: GlBackend::Egl,
        workers: 2,
        limits: Limits::default(),
        worker_call_timeout: Duration::from_secs(60),
        worker_create_timeout: Duration::from_secs(300),
        acting: radserve_core::ActingConfig::default(),
        replay: radserve_core::ReplayConfig::default(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_envpool_session_steps_asynchronously_through_the_workers() {
    let (_manager, pool) = radserve::session_manager(settings());
    let env = EnvId { family: Family::Gym, name: "CartPole-v1".into() };
    let overrides = Options::from([("engine".to_string(), OptionValue::Str("envpool".into()))]);
    let mut options = resolve_options(&env, &overrides).unwrap();
    options.insert(BATCH_SIZE.to_string(), OptionValue::Int(2));
    let frame_stack = options[FRAME_STACK].as_int().unwrap() as usize;
    let (n, batch) = (6usize, 2usize);
    let config = SessionConfig { env, num_envs: n, seed: 5, options, frame_stack };
    let mut session = Session::create(pool.as_ref(), config).await.expect("an envpool session");
    assert_eq!(session.async_batch(), Some(batch));
    let refused = session.reset(None).await.unwrap_err();
    assert!(refused.to_string().contains("async_reset"), "{refused}");

    session.async_reset(Some(5)).await.unwrap();
    let frame_bytes = 4 * 4; // CartPole: 4 float32
    let mut returned = vec![0usize; n];
    let mut firsts = Vec::new();
    let (mut ends, mut steps) = (0, 0);
    let mut reply = session.recv().await.unwrap();
    for round in 0..300 {
        let (ready, outcome) = reply;
        let envs: Vec<usize> = (0..n).filter(|&env| ready[env]).collect();
        assert_eq!(envs.len(), batch, "round {round}");
        for &env in &envs {
            if returned[env] == 0 {
                firsts.push(outcome.obs[env * frame_bytes..][..frame_bytes].to_vec());
                assert_eq!(outcome.rewards[env], 0.0, "a reset's first observation has no reward");
            } else {
                assert_eq!(outcome.rewards[env], 1.0, "CartPole pays 1 per step");
                steps += 1;
            }
            returned[env] += 1;
        }
        ends += outcome.episodes.len();
        assert_eq!(outcome.final_obs.len(), outcome.episodes.len() * frame_bytes);
        // Push left twice, then right: episodes end within tens of steps.
        let values: Vec<i64> = (0..n).map(|env| i64::from((returned[env] % 3) == 0)).collect();
        let actions: Vec<u8> = values.iter().flat_map(|value| value.to_le_bytes()).collect();
        if round == 299 {
            break;
        }
        // Half the rounds send and recv in two calls, half in one round trip (the worker's SendRecv).
        reply = if round % 2 == 0 {
            session.send(DType::Int64, &[n], &actions, &ready).await.unwrap();
            session.recv().await.unwrap()
        } else {
            session.send_recv(DType::Int64, &[n], &actions, &ready).await.unwrap()
        };
    }
    assert!(returned.iter().all(|&count| count > 0), "every env came back: {returned:?}");
    assert_eq!(firsts.len(), n);
    assert!(ends > 0, "the run covers episode ends");
    assert_eq!(session.total_env_steps(), steps as u64);
    assert_eq!(session.episodes_completed(), ends as u64);
    session.close().await;
    pool.stop().await;
}
