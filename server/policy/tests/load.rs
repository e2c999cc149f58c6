//! Models checked at load and run through ONNX Runtime (the wheel in the repository's .venv, or
//! the library RADSERVE_ONNXRUNTIME names). Fixtures: server/policy/tests/models, written by
//! tests/policies.py.

use std::path::{Path, PathBuf};

use std::time::Duration;

use radserve_policy::{library_of_python, ActionSpec, Head, ObservationSpec, ObservationType, Policy, PolicyError, PolicySpec, RuntimeLauncher};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn library() -> PathBuf {
    if let Ok(path) = std::env::var("RADSERVE_ONNXRUNTIME") {
        return PathBuf::from(path);
    }
    let python = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../.venv/bin/python");
    library_of_python(&python).expect("onnxruntime in the repository's .venv (make setup)")
}

/// This crate's runtime binary with 256 MiB (`memory_bytes`).
fn launcher_with(memory_bytes: u64) -> RuntimeLauncher {
    RuntimeLauncher {
        program: PathBuf::from(env!("CARGO_BIN_EXE_radserve-policy-runtime")),
        args: Vec::new(),
        library: library(),
        memory_bytes,
        load_timeout: Duration::from_secs(60),
        call_timeout: Duration::from_secs(30),
    }
}

fn launcher() -> RuntimeLauncher {
    launcher_with(256 << 20)
}

fn model(name: &str) -> Vec<u8> {
    std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/models").join(name)).expect("fixture")
}

fn fake_obs(num_envs: usize) -> ObservationSpec {
    ObservationSpec { num_envs, shape: vec![1, 2, 2], dtype: ObservationType::Uint8 }
}

fn categorical() -> PolicySpec {
    PolicySpec { head: Head::Categorical, threads: 1 }
}

async fn load(name: &str, spec: PolicySpec, observations: ObservationSpec, actions: ActionSpec) -> Result<Policy, PolicyError> {
    Policy::load(&launcher(), &model(name), spec, observations, actions).await
}

#[tokio::test]
async fn a_categorical_policy_acts_on_the_observations_it_is_given() {
    let mut policy = load("pick_first_byte.onnx", categorical(), fake_obs(3), ActionSpec::Discrete { n: 3 }).await.unwrap();
    let obs = [4u8, 0, 0, 0, 2, 9, 9, 9, 3, 1, 1, 1];
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let acted = policy.act(&obs, &mut rng, 0, false).await.unwrap();
    let actions: Vec<i64> = acted.actions.chunks(8).map(|b| i64::from_le_bytes(b.try_into().unwrap())).collect();
    assert_eq!(actions, vec![1, 2, 0]);
    assert!(acted.log_prob.iter().all(|p| p.abs() < 1e-3), "{:?}", acted.log_prob);
    assert_eq!(acted.value, None);
}

#[tokio::test]
async fn uint8_and_float_inputs_agree_and_the_value_output_is_returned() {
    let mut float = load("categorical_fake.onnx", categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).await.unwrap();
    let mut bytes = load("categorical_fake_u8.onnx", categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).await.unwrap();
    let obs = [10u8, 20, 30, 40, 200, 100, 50, 0];
    let a = float.act(&obs, &mut ChaCha8Rng::seed_from_u64(5), 0, false).await.unwrap();
    let b = bytes.act(&obs, &mut ChaCha8Rng::seed_from_u64(5), 0, false).await.unwrap();
    assert_eq!(a.actions, b.actions);
    assert!(float.has_value());
    assert_eq!(a.value.as_ref().map(Vec::len), Some(2));
}

#[tokio::test]
async fn the_same_seed_gives_the_same_actions() {
    let mut policy = load("categorical_fake.onnx", categorical(), fake_obs(4), ActionSpec::Discrete { n: 3 }).await.unwrap();
    let obs = vec![7u8; 16];
    async fn run(policy: &mut Policy, obs: &[u8], seed: u64) -> Vec<u8> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut actions = Vec::new();
        for _ in 0..20 {
            actions.extend(policy.act(obs, &mut rng, 0, false).await.unwrap().actions);
        }
        actions
    }
    let first = run(&mut policy, &obs, 1).await;
    assert_eq!(first, run(&mut policy, &obs, 1).await);
    assert_ne!(first, run(&mut policy, &obs, 2).await);
}

#[tokio::test]
async fn a_gaussian_policy_scales_its_actions_onto_the_bounds() {
    let actions = ActionSpec::Box { dims: 2, low: vec![-2.0, 0.0], high: vec![2.0, 10.0], float64: false };
    let spec = PolicySpec { head: Head::GaussianTanh, threads: 1 };
    let observations = ObservationSpec { num_envs: 5, shape: vec![3], dtype: ObservationType::Float64 };
    let mut policy = load("gaussian_3x2.onnx", spec, observations, actions).await.unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let obs: Vec<u8> = (0..15).flat_map(|i| (f64::from(i) * 0.1).to_le_bytes()).collect();
    for _ in 0..50 {
        let acted = policy.act(&obs, &mut rng, 0, false).await.unwrap();
        let values: Vec<f32> = acted.actions.chunks(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
        assert_eq!(values.len(), 10);
        for pair in values.chunks(2) {
            assert!((-2.0..=2.0).contains(&pair[0]) && (0.0..=10.0).contains(&pair[1]), "{pair:?}");
        }
        assert!(acted.log_prob.iter().all(|p| p.is_finite()));
    }
}

#[tokio::test]
async fn refusals_name_what_is_wrong() {
    let discrete = ActionSpec::Discrete { n: 3 };
    let message = |result: Result<Policy, PolicyError>| result.expect_err("refused").to_string();
    let text = message(load("random_op_fake.onnx", categorical(), fake_obs(2), discrete.clone()).await);
    assert!(text.contains("RandomNormalLike"), "{text}");
    let text = message(load("external_fake.onnx", categorical(), fake_obs(2), discrete.clone()).await);
    assert!(text.contains("external data"), "{text}");
    let text = message(load("categorical_fake.onnx", categorical(), ObservationSpec { num_envs: 2, shape: vec![3, 2, 2], dtype: ObservationType::Uint8 }, discrete.clone()).await);
    assert!(text.contains("does not take this session's observations") && text.contains("3, 2, 2"), "{text}");
    let text = message(load("categorical_fake.onnx", categorical(), fake_obs(2), ActionSpec::Discrete { n: 4 }).await);
    assert!(text.contains("output 'logits' has shape [2, 3]"), "{text}");
    let spec = PolicySpec { head: Head::GaussianTanh, threads: 1 };
    let text = message(load("categorical_fake.onnx", spec, fake_obs(2), discrete.clone()).await);
    assert!(text.contains("use categorical"), "{text}");
    let text = message(Policy::load(&launcher(), b"not a model at all", categorical(), fake_obs(2), discrete.clone()).await);
    assert!(text.starts_with("not an ONNX model"), "{text}");
    let text = message(Policy::load(&launcher(), &[], categorical(), fake_obs(2), discrete).await);
    assert!(text.starts_with("not an ONNX model"), "{text}");
}

#[tokio::test]
async fn a_policy_that_turns_nan_says_so_when_it_acts() {
    let mut policy = load("nan_fake.onnx", categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).await.unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    policy.act(&[0u8; 8], &mut rng, 0, false).await.unwrap();
    let error = policy.act(&[0, 0, 0, 0, 1, 0, 0, 0], &mut rng, 0, false).await.unwrap_err();
    assert!(matches!(&error, PolicyError::NonFinite(message) if message.contains("output 'logits' of env 1 is NaN")), "{error}");
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig { cases: 100, ..Default::default() })]

    /// The whole load, ONNX Runtime included, on a real model with bytes changed: a policy or a
    /// refusal, never a crash (a model that still passes the checks must also run finite on zeros).
    #[test]
    fn damaged_models_load_or_are_refused(flips in proptest::collection::vec((0usize..1092, proptest::prelude::any::<u8>()), 1..6)) {
        let mut bytes = model("categorical_fake.onnx");
        for (at, value) in flips {
            let at = at % bytes.len();
            bytes[at] = value;
        }
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        runtime.block_on(async {
            if let Ok(mut policy) = Policy::load(&launcher(), &bytes, categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).await {
                let _ = policy.act(&[9u8; 8], &mut ChaCha8Rng::seed_from_u64(0), 0, false).await;
            }
        });
    }
}

/// The runtime binary started in `dir` with `flags` (steps of containment left out).
fn launcher_in(dir: &Path, flags: &[&str]) -> RuntimeLauncher {
    let mut launcher = launcher();
    launcher.args = ["--chdir", dir.to_str().unwrap()].iter().chain(flags).map(|arg| arg.to_string()).collect();
    launcher
}

/// The value output of `sparse_external_fake.onnx` (its sparse Constant reads four float32 from
/// `creds.txt`, relative to the working directory) run in a runtime started in `dir` with `flags`.
async fn exfiltrate(dir: &Path, flags: &[&str]) -> Result<f32, PolicyError> {
    let data: Vec<u8> = [0.0f32; 4].iter().flat_map(|value| value.to_le_bytes()).collect();
    let outputs = Policy::run_unchecked(&launcher_in(dir, flags), &model("sparse_external_fake.onnx"), vec![1, 1, 2, 2], false, data).await?;
    Ok(outputs[1].1[0])
}

#[tokio::test]
async fn a_model_cannot_read_a_file_even_past_the_checks() {
    let dir = std::env::temp_dir().join(format!("radserve-exfiltration-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let secret: Vec<u8> = [1e6f32, 2e6, 3e6, 4e6].iter().flat_map(|value| value.to_le_bytes()).collect();
    std::fs::write(dir.join("creds.txt"), &secret).unwrap();
    // The control: with both steps of containment left out, ONNX Runtime reads the file (the
    // probe works, so the assertions below can fail).
    let leaked = exfiltrate(&dir, &["--keep-working-directory", "--allow-files"]).await.unwrap();
    assert!(leaked > 9e6, "the control should read creds.txt: {leaked}");
    // Each step alone keeps it unread: the seccomp filter (the file is right there in the working
    // directory), the removed working directory (nothing to open), and both.
    for flags in [&["--keep-working-directory"][..], &["--allow-files"][..], &[][..]] {
        let result = exfiltrate(&dir, flags).await;
        assert!(result.is_err(), "{flags:?}: the model read the file: {result:?}");
    }
    // Through the server's load, the check refuses it first, naming where the file is named.
    let text = load("sparse_external_fake.onnx", categorical(), fake_obs(1), ActionSpec::Discrete { n: 3 }).await.unwrap_err().to_string();
    assert!(text.contains("external data") && text.contains("attribute 'sparse_value'") && text.contains("node 'leak'"), "{text}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test]
async fn models_that_allocate_without_bound_are_refused_at_the_limit() {
    // A few hundred bytes each; gigabytes at constant folding. Refused at load with the limit named.
    for name in ["concat_bomb_fake.onnx", "broadcast_bomb_fake.onnx"] {
        let result = Policy::load(&launcher_with(256 << 20), &model(name), categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).await;
        let error = result.expect_err(name);
        assert!(matches!(&error, PolicyError::Exhausted(message) if message.contains("268435456 bytes a policy may use")), "{name}: {error}");
    }
    // One sized from the observations: nothing on the zero observations of the load, past the
    // limit at the first real frame, where acting fails and the policy runtime with it.
    let mut policy = Policy::load(&launcher_with(256 << 20), &model("pad_bomb_fake.onnx"), categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).await.unwrap();
    let error = policy.act(&[255u8; 8], &mut ChaCha8Rng::seed_from_u64(0), 0, false).await.unwrap_err();
    assert!(matches!(&error, PolicyError::Exhausted(message) if message.contains("268435456")), "{error}");
    // A limit below ONNX Runtime's own needs refuses even a small model, saying so.
    let error = Policy::load(&launcher_with(8 << 20), &model("categorical_fake.onnx"), categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).await.unwrap_err();
    assert!(matches!(&error, PolicyError::Exhausted(_)), "{error}");
}

#[tokio::test]
async fn a_runtime_that_stops_answering_is_stopped_at_the_deadline() {
    // A runtime that never answers: `sleep` in its place (the deadline, not the model, is tested).
    let launcher = RuntimeLauncher { program: PathBuf::from("sh"), args: vec!["-c".into(), "exec sleep 30".into()], load_timeout: Duration::from_millis(500), ..launcher() };
    let started = std::time::Instant::now();
    let error = Policy::load(&launcher, &model("categorical_fake.onnx"), categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).await.unwrap_err();
    assert!(started.elapsed() < Duration::from_secs(5), "{:?}", started.elapsed());
    assert!(matches!(&error, PolicyError::Exhausted(message) if message.contains("acting.policy_load_timeout_s")), "{error}");
}
