//! Models checked at load and run through ONNX Runtime (the wheel in the repository's .venv, or
//! the library RADSERVE_ONNXRUNTIME names). Fixtures: server/policy/tests/models, written by
//! tests/policies.py.

use std::path::{Path, PathBuf};

use radserve_policy::{library_of_python, runtime, ActionSpec, Head, ObservationSpec, ObservationType, Policy, PolicyError, PolicySpec};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn library() -> PathBuf {
    if let Ok(path) = std::env::var("RADSERVE_ONNXRUNTIME") {
        return PathBuf::from(path);
    }
    let python = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../.venv/bin/python");
    library_of_python(&python).expect("onnxruntime in the repository's .venv (make setup)")
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

fn load(name: &str, spec: PolicySpec, observations: ObservationSpec, actions: ActionSpec) -> Result<Policy, PolicyError> {
    Policy::load(runtime(|| Ok(library())).expect("ONNX Runtime"), &model(name), spec, observations, actions)
}

#[test]
fn a_categorical_policy_acts_on_the_observations_it_is_given() {
    let mut policy = load("pick_first_byte.onnx", categorical(), fake_obs(3), ActionSpec::Discrete { n: 3 }).unwrap();
    let obs = [4u8, 0, 0, 0, 2, 9, 9, 9, 3, 1, 1, 1];
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let acted = policy.act(&obs, &mut rng, 0, false).unwrap();
    let actions: Vec<i64> = acted.actions.chunks(8).map(|b| i64::from_le_bytes(b.try_into().unwrap())).collect();
    assert_eq!(actions, vec![1, 2, 0]);
    assert!(acted.log_prob.iter().all(|p| p.abs() < 1e-3), "{:?}", acted.log_prob);
    assert_eq!(acted.value, None);
}

#[test]
fn uint8_and_float_inputs_agree_and_the_value_output_is_returned() {
    let mut float = load("categorical_fake.onnx", categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).unwrap();
    let mut bytes = load("categorical_fake_u8.onnx", categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).unwrap();
    let obs = [10u8, 20, 30, 40, 200, 100, 50, 0];
    let a = float.act(&obs, &mut ChaCha8Rng::seed_from_u64(5), 0, false).unwrap();
    let b = bytes.act(&obs, &mut ChaCha8Rng::seed_from_u64(5), 0, false).unwrap();
    assert_eq!(a.actions, b.actions);
    assert!(float.has_value());
    assert_eq!(a.value.as_ref().map(Vec::len), Some(2));
}

#[test]
fn the_same_seed_gives_the_same_actions() {
    let mut policy = load("categorical_fake.onnx", categorical(), fake_obs(4), ActionSpec::Discrete { n: 3 }).unwrap();
    let obs = vec![7u8; 16];
    let run = |policy: &mut Policy, seed| {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..20).flat_map(|_| policy.act(&obs, &mut rng, 0, false).unwrap().actions).collect::<Vec<u8>>()
    };
    let first = run(&mut policy, 1);
    assert_eq!(first, run(&mut policy, 1));
    assert_ne!(first, run(&mut policy, 2));
}

#[test]
fn a_gaussian_policy_scales_its_actions_onto_the_bounds() {
    let actions = ActionSpec::Box { dims: 2, low: vec![-2.0, 0.0], high: vec![2.0, 10.0], float64: false };
    let spec = PolicySpec { head: Head::GaussianTanh, threads: 1 };
    let observations = ObservationSpec { num_envs: 5, shape: vec![3], dtype: ObservationType::Float64 };
    let mut policy = load("gaussian_3x2.onnx", spec, observations, actions).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let obs: Vec<u8> = (0..15).flat_map(|i| (f64::from(i) * 0.1).to_le_bytes()).collect();
    for _ in 0..50 {
        let acted = policy.act(&obs, &mut rng, 0, false).unwrap();
        let values: Vec<f32> = acted.actions.chunks(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
        assert_eq!(values.len(), 10);
        for pair in values.chunks(2) {
            assert!((-2.0..=2.0).contains(&pair[0]) && (0.0..=10.0).contains(&pair[1]), "{pair:?}");
        }
        assert!(acted.log_prob.iter().all(|p| p.is_finite()));
    }
}

#[test]
fn refusals_name_what_is_wrong() {
    let discrete = ActionSpec::Discrete { n: 3 };
    let message = |result: Result<Policy, PolicyError>| result.expect_err("refused").to_string();
    let text = message(load("random_op_fake.onnx", categorical(), fake_obs(2), discrete.clone()));
    assert!(text.contains("RandomNormalLike"), "{text}");
    let text = message(load("external_fake.onnx", categorical(), fake_obs(2), discrete.clone()));
    assert!(text.contains("external data"), "{text}");
    let text = message(load("categorical_fake.onnx", categorical(), ObservationSpec { num_envs: 2, shape: vec![3, 2, 2], dtype: ObservationType::Uint8 }, discrete.clone()));
    assert!(text.contains("does not take this session's observations") && text.contains("3, 2, 2"), "{text}");
    let text = message(load("categorical_fake.onnx", categorical(), fake_obs(2), ActionSpec::Discrete { n: 4 }));
    assert!(text.contains("output 'logits' has shape [2, 3]"), "{text}");
    let spec = PolicySpec { head: Head::GaussianTanh, threads: 1 };
    let text = message(load("categorical_fake.onnx", spec, fake_obs(2), discrete.clone()));
    assert!(text.contains("use categorical"), "{text}");
    let text = message(Policy::load(runtime(|| Ok(library())).unwrap(), b"not a model at all", categorical(), fake_obs(2), discrete.clone()));
    assert!(text.starts_with("not an ONNX model"), "{text}");
    let text = message(Policy::load(runtime(|| Ok(library())).unwrap(), &[], categorical(), fake_obs(2), discrete));
    assert!(text.starts_with("not an ONNX model"), "{text}");
}

#[test]
fn a_policy_that_turns_nan_says_so_when_it_acts() {
    let mut policy = load("nan_fake.onnx", categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    policy.act(&[0u8; 8], &mut rng, 0, false).unwrap();
    let error = policy.act(&[0, 0, 0, 0, 1, 0, 0, 0], &mut rng, 0, false).unwrap_err();
    assert!(matches!(&error, PolicyError::NonFinite(message) if message.contains("output 'logits' of env 1 is NaN")), "{error}");
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig { cases: 300, ..Default::default() })]

    /// The whole load, ONNX Runtime included, on a real model with bytes changed: a policy or a
    /// refusal, never a crash (a model that still passes the checks must also run finite on zeros).
    #[test]
    fn damaged_models_load_or_are_refused(flips in proptest::collection::vec((0usize..1092, proptest::prelude::any::<u8>()), 1..6)) {
        let mut bytes = model("categorical_fake.onnx");
        for (at, value) in flips {
            let at = at % bytes.len();
            bytes[at] = value;
        }
        if let Ok(mut policy) = Policy::load(runtime(|| Ok(library())).unwrap(), &bytes, categorical(), fake_obs(2), ActionSpec::Discrete { n: 3 }) {
            let _ = policy.act(&[9u8; 8], &mut ChaCha8Rng::seed_from_u64(0), 0, false);
        }
    }
}
