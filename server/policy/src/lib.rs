//! Policies a learner sends to the server (SetPolicy), for the server's own actors: an ONNX model
//! (torch.onnx.export of the learner's actor) with a declared head.
//!
//! A model is checked in two steps, both at load: its structure from its bytes (`model::inspect`:
//! opset, operators, no external data, one input), then against the session (the input takes the
//! session's observations, the outputs are what the head needs, sized for the action space), then
//! ONNX Runtime builds it and it is run once on zero observations, whose outputs must be finite and
//! of the declared shapes. Nothing about the model can fail later except its numbers: an output that
//! is not finite stops the actor (`PolicyError::NonFinite`).
//!
//! Inference runs in ONNX Runtime, loaded from the `onnxruntime` wheel installed beside the
//! workers' Python (or a library path in the configuration), in a process of its own per policy
//! that can open no file and use no more memory than its session was charged ([`runtime`] says how;
//! [`RuntimeLauncher`] starts it). The server itself never loads a model.

use std::path::{Path, PathBuf};

use rand::Rng;

pub mod head;
pub mod model;
mod process;
pub mod runtime;

pub use head::Head;
pub use model::{inspect, ModelSummary, SUPPORTED_OPS};
pub use process::RuntimeLauncher;

#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum PolicyError {
    #[error("not an ONNX model: {0}")]
    NotOnnx(String),
    #[error("unsupported model: {0}")]
    Unsupported(String),
    #[error("the model does not fit this session: {0}")]
    Mismatch(String),
    #[error("ONNX Runtime refused the model: {0}")]
    Runtime(String),
    #[error("the policy produced a value that is not finite: {0}")]
    NonFinite(String),
    #[error("ONNX Runtime is not available on this server: {0}")]
    Unavailable(String),
    /// Past a limit of the policy runtime: its memory, or the time to load or to act.
    #[error("the policy is over this server's limits: {0}")]
    Exhausted(String),
}

/// The observations a session's policy acts on: `[num_envs, *shape]` of `dtype` (stacked frames
/// through the session's view, or state vectors).
#[derive(Clone, Debug, PartialEq)]
pub struct ObservationSpec {
    pub num_envs: usize,
    pub shape: Vec<usize>,
    pub dtype: ObservationType,
}

/// The element type of a session's observations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum ObservationType {
    Uint8,
    Float32,
    Float64,
}

impl ObservationType {
    fn size(self) -> usize {
        match self {
            ObservationType::Uint8 => 1,
            ObservationType::Float32 => 4,
            ObservationType::Float64 => 8,
        }
    }

    fn name(self) -> &'static str {
        match self {
            ObservationType::Uint8 => "uint8",
            ObservationType::Float32 => "float32",
            ObservationType::Float64 => "float64",
        }
    }

    /// Little-endian observation bytes as the float32 a model takes.
    pub(crate) fn to_f32(self, bytes: &[u8]) -> Vec<f32> {
        match self {
            ObservationType::Uint8 => bytes.iter().map(|&byte| f32::from(byte)).collect(),
            ObservationType::Float32 => bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
            ObservationType::Float64 => {
                bytes.chunks_exact(8).map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32).collect()
            }
        }
    }
}

/// The actions it must produce.
#[derive(Clone, Debug, PartialEq)]
pub enum ActionSpec {
    /// gymnasium's Discrete(n), sent as int64.
    Discrete { n: usize },
    /// A flat Box of `dims` elements with finite bounds, each of `float64` when set, else float32.
    Box { dims: usize, low: Vec<f64>, high: Vec<f64>, float64: bool },
}

impl ActionSpec {
    fn dims(&self) -> usize {
        match self {
            ActionSpec::Discrete { n } => *n,
            ActionSpec::Box { dims, .. } => *dims,
        }
    }

    /// Bytes of one env's action.
    pub fn action_bytes(&self) -> usize {
        match self {
            ActionSpec::Discrete { .. } => 8,
            ActionSpec::Box { dims, float64, .. } => dims * if *float64 { 8 } else { 4 },
        }
    }

    fn bound(values: &[f64], i: usize) -> f64 {
        if values.len() == 1 {
            values[0]
        } else {
            values[i]
        }
    }

    /// Writes a unit-interval action (each element in [-1, 1]) scaled onto the bounds.
    fn write_box(&self, unit: &[f32], out: &mut Vec<u8>) {
        if let ActionSpec::Box { low, high, float64, .. } = self {
            for (i, value) in unit.iter().enumerate() {
                let scaled = head::scale(*value, Self::bound(low, i), Self::bound(high, i));
                if *float64 {
                    out.extend_from_slice(&scaled.to_le_bytes());
                } else {
                    out.extend_from_slice(&(scaled as f32).to_le_bytes());
                }
            }
        }
    }

    /// Uniformly random actions for `num_envs` envs (the warm-up steps before the policy acts).
    pub fn random(&self, num_envs: usize, rng: &mut impl Rng) -> Vec<u8> {
        let mut out = Vec::with_capacity(num_envs * self.action_bytes());
        for _ in 0..num_envs {
            match self {
                ActionSpec::Discrete { n } => out.extend_from_slice(&(rng.random_range(0..*n) as i64).to_le_bytes()),
                ActionSpec::Box { dims, .. } => {
                    let unit: Vec<f32> = (0..*dims).map(|_| rng.random_range(-1.0f32..=1.0)).collect();
                    self.write_box(&unit, &mut out);
                }
            }
        }
        out
    }
}

/// What SetPolicy declares beside the model.
#[derive(Clone, Debug, PartialEq)]
pub struct PolicySpec {
    pub head: Head,
    /// Intra-op threads of ONNX Runtime for this model (1: inference on the runtime process's main
    /// thread).
    pub threads: usize,
}

/// One step's actions for every env, with what the head computed beside them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Acted {
    /// [num_envs, *action] in the action space's dtype, little-endian.
    pub actions: Vec<u8>,
    /// The head's log-probability of each env's action (0 for `deterministic_noise`).
    pub log_prob: Vec<f32>,
    /// The model's value output, when it has one.
    pub value: Option<Vec<f32>>,
}

/// The ONNX Runtime library of the `onnxruntime` wheel installed for `python`, found without
/// importing the package (its `capi/libonnxruntime.so.*`).
pub fn library_of_python(python: &Path) -> Result<PathBuf, PolicyError> {
    let output = std::process::Command::new(python)
        .args(["-c", "import importlib.util as u; s = u.find_spec('onnxruntime'); print(s.submodule_search_locations[0] if s else '')"])
        .output()
        .map_err(|error| PolicyError::Unavailable(format!("running {}: {error}", python.display())))?;
    let package = String::from_utf8_lossy(&output.stdout).trim().to_string();
    if package.is_empty() {
        return Err(PolicyError::Unavailable(format!(
            "the onnxruntime package is not installed for {} (pip install onnxruntime, or set acting.onnxruntime_library)",
            python.display()
        )));
    }
    let capi = Path::new(&package).join("capi");
    let mut found: Vec<PathBuf> = std::fs::read_dir(&capi)
        .map_err(|error| PolicyError::Unavailable(format!("reading {}: {error}", capi.display())))?
        .filter_map(|entry| entry.ok().map(|entry| entry.path()))
        .filter(|path| path.file_name().and_then(|name| name.to_str()).is_some_and(|name| name.starts_with("libonnxruntime.so")))
        .collect();
    found.sort();
    found.pop().ok_or_else(|| PolicyError::Unavailable(format!("no libonnxruntime.so in {}", capi.display())))
}

/// A loaded policy for one session: its checked summary and the runtime process that holds it.
pub struct Policy {
    runtime: process::RuntimeProcess,
    pub summary: ModelSummary,
    pub spec: PolicySpec,
    observations: ObservationSpec,
    actions: ActionSpec,
    input_uint8: bool,
    has_value: bool,
}

impl std::fmt::Debug for Policy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Policy").field("head", &self.spec.head).field("summary", &self.summary).finish()
    }
}

/// Checks the model's declared input and outputs against the session and the head.
fn check_ports(summary: &ModelSummary, spec: &PolicySpec, observations: &ObservationSpec, actions: &ActionSpec) -> Result<bool, PolicyError> {
    let input = &summary.input;
    let uint8_allowed = observations.dtype == ObservationType::Uint8;
    if input.elem != model::ELEM_FLOAT && !(input.elem == model::ELEM_UINT8 && uint8_allowed) {
        return Err(PolicyError::Mismatch(format!(
            "the input {} must be float32 ({}){}",
            input.describe(),
            if uint8_allowed { "raw 0..255 values; the model divides by 255 itself, as RAD's encoder does" } else { "the session's observations converted" },
            if uint8_allowed { " or uint8" } else { "" },
        )));
    }
    if let Some(dims) = &input.dims {
        let expected = observations.shape.len() + 1;
        let fits = dims.len() == expected
            && match &dims[0] {
                model::Dim::Fixed(batch) => *batch == observations.num_envs as i64,
                model::Dim::Named(_) | model::Dim::Unknown => true,
            }
            && dims[1..].iter().zip(&observations.shape).all(|(dim, size)| match dim {
                model::Dim::Fixed(value) => *value == *size as i64,
                model::Dim::Named(_) | model::Dim::Unknown => true,
            });
        if !fits {
            return Err(PolicyError::Mismatch(format!(
                "the input {} does not take this session's observations: [batch, {}] with batch {} (num_envs) or a dynamic \
                 axis (torch.onnx.export(..., dynamic_axes={{'obs': {{0: 'batch'}}}}))",
                input.describe(),
                observations.shape.iter().map(usize::to_string).collect::<Vec<_>>().join(", "),
                observations.num_envs
            )));
        }
    }
    match (&spec.head, actions) {
        (Head::Categorical, ActionSpec::Discrete { .. }) => {}
        (Head::GaussianTanh | Head::DeterministicNoise { .. }, ActionSpec::Box { low, high, .. }) => {
            if low.iter().chain(high).any(|bound| !bound.is_finite()) {
                return Err(PolicyError::Mismatch(format!(
                    "head {} scales actions onto the action space's bounds, and this session's are not finite",
                    spec.head.name()
                )));
            }
        }
        (head, ActionSpec::Discrete { n }) => {
            return Err(PolicyError::Mismatch(format!("head {} is for continuous actions; this session's are Discrete({n}): use categorical", head.name())))
        }
        (head, ActionSpec::Box { dims, .. }) => {
            return Err(PolicyError::Mismatch(format!(
                "head {} is for discrete actions; this session's are a Box of {dims}: use gaussian_tanh or deterministic_noise",
                head.name()
            )))
        }
    }
    let (required, optional) = spec.head.outputs();
    let allowed = required.len() + usize::from(optional.is_some());
    if summary.outputs.len() < required.len() || summary.outputs.len() > allowed {
        return Err(PolicyError::Mismatch(format!(
            "head {} needs the outputs ({}){}, in this order; the model has {}: {}",
            spec.head.name(),
            required.join(", "),
            optional.map(|name| format!(" and optionally {name}")).unwrap_or_default(),
            summary.outputs.len(),
            summary.outputs.iter().map(model::Port::describe).collect::<Vec<_>>().join(", ")
        )));
    }
    if let Some(output) = summary.outputs.iter().find(|output| output.elem != model::ELEM_FLOAT) {
        return Err(PolicyError::Mismatch(format!("output {} must be float32", output.describe())));
    }
    Ok(summary.outputs.len() > required.len())
}

impl Policy {
    /// Checks `bytes` for a session whose observations and actions are `observations` and
    /// `actions`, builds it in a policy runtime of its own, then runs it once on zeros.
    pub async fn load(
        launcher: &RuntimeLauncher,
        bytes: &[u8],
        spec: PolicySpec,
        observations: ObservationSpec,
        actions: ActionSpec,
    ) -> Result<Policy, PolicyError> {
        let summary = inspect(bytes)?;
        let has_value = check_ports(&summary, &spec, &observations, &actions)?;
        // The outputs a run of this session can answer with (every output at most num_envs x the
        // action size of float32, with room for the encoding), or an error message.
        let per_output = observations.num_envs * actions.dims().max(1) * 4 + 64;
        let max_reply = (summary.outputs.len() * per_output).max(64 << 10) + 4096;
        let runtime = process::RuntimeProcess::start(launcher, bytes, spec.threads, max_reply).await?;
        let input_uint8 = summary.input.elem == model::ELEM_UINT8;
        let mut policy = Policy { runtime, summary, spec, observations, actions, input_uint8, has_value };
        let zeros = vec![0u8; policy.observation_bytes()];
        let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
        policy.act(&zeros, &mut rng, 0, true).await.map_err(|error| match error {
            PolicyError::NonFinite(message) => PolicyError::NonFinite(format!("on zero observations: {message}")),
            other @ (PolicyError::NotOnnx(_)
            | PolicyError::Unsupported(_)
            | PolicyError::Mismatch(_)
            | PolicyError::Runtime(_)
            | PolicyError::Unavailable(_)
            | PolicyError::Exhausted(_)) => other,
        })?;
        Ok(policy)
    }

    /// Runs `model` once on `data` in a runtime of its own, without any of the server's checks: for
    /// the tests that show the runtime contains what a check might miss.
    #[doc(hidden)]
    pub async fn run_unchecked(launcher: &RuntimeLauncher, model: &[u8], shape: Vec<i64>, uint8: bool, data: Vec<u8>) -> Result<Vec<(Vec<i64>, Vec<f32>)>, PolicyError> {
        let mut runtime = process::RuntimeProcess::start(launcher, model, 1, 1 << 20).await?;
        let dtype = if uint8 { ObservationType::Uint8 } else { ObservationType::Float32 };
        let outputs = runtime.run(shape, dtype, uint8, &data).await?;
        Ok(outputs.into_iter().map(|output| (output.shape, output.values)).collect())
    }

    /// Whether the policy can act again: false once its runtime was stopped (past a limit, or gone).
    pub fn usable(&self) -> bool {
        self.runtime.alive()
    }

    /// The policy runtime's peak resident memory at its last answer.
    pub fn peak_bytes(&self) -> u64 {
        self.runtime.peak_bytes
    }

    /// Bytes of one step's observations of every env.
    pub fn observation_bytes(&self) -> usize {
        self.observations.num_envs * self.observations.shape.iter().product::<usize>() * self.observations.dtype.size()
    }

    pub fn head(&self) -> &Head {
        &self.spec.head
    }

    /// Whether the model has a value output (recorded with PPO rollouts).
    pub fn has_value(&self) -> bool {
        self.has_value
    }

    /// The actions of every env for `obs` ([num_envs, *observation] uint8): the model run once on
    /// the batch, then the head per env. `env_steps` (the session's so far) sets the deterministic
    /// head's noise; `eval` acts without exploration.
    pub async fn act(&mut self, obs: &[u8], rng: &mut (impl Rng + Send), env_steps: u64, eval: bool) -> Result<Acted, PolicyError> {
        if obs.len() != self.observation_bytes() {
            return Err(PolicyError::Mismatch(format!(
                "{} bytes of observations; this policy takes {} ({} {:?} per env)",
                obs.len(),
                self.observation_bytes(),
                self.observations.dtype.name(),
                self.observations.shape
            )));
        }
        let num_envs = self.observations.num_envs;
        let shape: Vec<i64> = std::iter::once(num_envs).chain(self.observations.shape.iter().copied()).map(|d| d as i64).collect();
        let outputs = self.runtime.run(shape, self.observations.dtype, self.input_uint8, obs).await?;
        if outputs.len() != self.summary.outputs.len() {
            return Err(PolicyError::Runtime(format!("the model answered {} outputs; its graph declares {}", outputs.len(), self.summary.outputs.len())));
        }
        let mut tensors: Vec<(String, Vec<f32>)> = Vec::with_capacity(outputs.len());
        let dims = self.actions.dims();
        for ((index, port), output) in self.summary.outputs.iter().enumerate().zip(outputs) {
            let is_value = index >= self.spec.head.outputs().0.len();
            let expected: &[&[i64]] = if is_value { &[&[num_envs as i64], &[num_envs as i64, 1]] } else { &[&[num_envs as i64, dims as i64]] };
            let elements = output.shape.iter().try_fold(1i64, |product, &dim| product.checked_mul(dim));
            if !expected.iter().any(|shape| **shape == *output.shape) || elements != Some(output.values.len() as i64) {
                return Err(PolicyError::Mismatch(format!(
                    "output '{}' has shape {:?}; head {} needs {:?} (num_envs, {})",
                    port.name,
                    output.shape,
                    self.spec.head.name(),
                    expected[0],
                    if is_value { "a value per env" } else { "the action size" }
                )));
            }
            let values = output.values;
            if let Some(position) = values.iter().position(|value| !value.is_finite()) {
                return Err(PolicyError::NonFinite(format!(
                    "output '{}' of env {} is {}",
                    port.name,
                    position / (values.len() / num_envs).max(1),
                    values[position]
                )));
            }
            tensors.push((port.name.clone(), values));
        }
        let mut acted = Acted {
            actions: Vec::with_capacity(num_envs * self.actions.action_bytes()),
            log_prob: Vec::with_capacity(num_envs),
            value: self.has_value.then(|| tensors.last().map(|(_, values)| values.clone()).unwrap_or_default()),
        };
        let mut unit = vec![0.0f32; dims];
        for env in 0..num_envs {
            let row = |index: usize| &tensors[index].1[env * dims..(env + 1) * dims];
            match &self.spec.head {
                Head::GaussianTanh => {
                    acted.log_prob.push(head::gaussian_tanh(row(0), row(1), rng, eval, &mut unit));
                    self.actions.write_box(&unit, &mut acted.actions);
                }
                Head::Categorical => {
                    let (choice, log_prob) = head::categorical(row(0), rng, eval);
                    acted.log_prob.push(log_prob);
                    acted.actions.extend_from_slice(&(choice as i64).to_le_bytes());
                }
                Head::DeterministicNoise { clip, .. } => {
                    head::deterministic_noise(row(0), self.spec.head.noise_std(env_steps), *clip, rng, eval, &mut unit);
                    acted.log_prob.push(0.0);
                    self.actions.write_box(&unit, &mut acted.actions);
                }
            }
        }
        Ok(acted)
    }
}
