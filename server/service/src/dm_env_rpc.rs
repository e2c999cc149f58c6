//! DeepMind's dm_env_rpc protocol, version 1 (`dm_env_rpc.v1.Environment`), served beside
//! radserve's own API on the same port: a thin transport over the same core, so that an unmodified
//! dm_env_rpc client (`dm_env_rpc.v1.connection`, `dm_env_adaptor`) acts in any radserve env.
//!
//! The mapping (docs/dm_env_rpc.md), following the protocol's documentation
//! (github.com/google-deepmind/dm_env_rpc, docs/v1/overview.md and appendix.md):
//! - a **world** is a radserve session (`world_name` is its session id, owned by the caller like any
//!   session): CreateWorld settings `env_id` (string, required), `seed` (integer, default 0),
//!   `num_envs` (default 1) and any env option by its name (`frame_stack`, `action_repeat`, ...);
//! - JoinWorld binds the stream to one env of the world (setting `env_index`, default 0); one stream
//!   per env at a time; the stream's steps step that env alone (the others are skipped);
//! - specs: one action `action` (uid 1), observations `observation` (uid 1) and `reward` (uid 2, a
//!   float64 scalar). There is no `discount` observation: dm_env wants none on a FIRST step, and
//!   the state says it (TERMINATED: 0, RUNNING and INTERRUPTED: 1), as `dm_env_adaptor` computes it;
//! - the first Step after JoinWorld returns the env's current observation, and the first after
//!   Reset, an episode's end or a ResetWorld the new episode's first (RUNNING), ignoring the
//!   actions (the protocol's rule); Reset's setting `seed` seeds that episode; a step that ends an episode
//!   returns its last observation with TERMINATED (a terminal state) or INTERRUPTED (truncation, a
//!   simulator error);
//! - errors travel in-band (`EnvironmentResponse.error`) and the stream goes on; a malformed stream
//!   (undecodable bytes) ends with its gRPC status.

use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex};

use radserve_core::bounds::{check_count, check_len, MAX_ID_BYTES, MAX_OPTIONS, MAX_OPTION_NAME_BYTES, MAX_OPTION_TEXT_BYTES};
use radserve_core::actions::{validate_actions, MAX_SEED};
use radserve_core::session::Session;
use radserve_core::{DType, LeaseHold, OptionValue, Options, Principal, ResetSpec, SessionExtras, SessionManager, Space};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};
use tracing::debug;

use crate::error::{Result, ServiceError};
use crate::handlers::{caller, next_or_stop, send_or_stop};
use crate::pb::dm_env_rpc::v1 as dm;
use crate::pb::google::rpc as rpc;
use dm::environment_request::Payload as Inbound;
use dm::environment_response::Payload as Outbound;
use dm::tensor::Payload as TensorPayload;
use dm::tensor_spec::value::Payload as BoundPayload;

/// The one action of every world.
pub const ACTION_UID: u64 = 1;
pub const OBSERVATION_UID: u64 = 1;
pub const REWARD_UID: u64 = 2;
const ACTION_NAME: &str = "action";
const OBSERVATION_NAME: &str = "observation";
const REWARD_NAME: &str = "reward";

/// Responses that may wait for the client to read them.
const STREAM_BUFFER: usize = 2;
/// Most entries of a settings map, an actions map or a requested_observations list.
const MAX_ENTRIES: usize = MAX_OPTIONS + 8;

/// Which envs of which worlds a stream has joined, and how often each world was reset as a whole.
#[derive(Default)]
struct Worlds {
    joined: HashMap<String, World>,
}

#[derive(Default)]
struct World {
    seats: BTreeSet<usize>,
    /// ResetWorld calls while someone was joined: a joined stream that sees a new count starts a
    /// new episode at its next step.
    resets: u64,
}

type SharedWorlds = Arc<Mutex<Worlds>>;

/// A stream's place in a world; leaving (or the stream ending) frees it.
struct Seat {
    worlds: SharedWorlds,
    world: String,
    env: usize,
}

impl Drop for Seat {
    fn drop(&mut self) {
        let mut worlds = self.worlds.lock().expect("worlds lock");
        if let Some(world) = worlds.joined.get_mut(&self.world) {
            world.seats.remove(&self.env);
            if world.seats.is_empty() {
                worlds.joined.remove(&self.world);
            }
        }
    }
}

#[derive(Clone)]
pub struct EnvironmentService {
    manager: Arc<SessionManager>,
    worlds: SharedWorlds,
    stopping: watch::Receiver<bool>,
}

impl EnvironmentService {
    /// `stopping` turns true when the server begins to shut down (the RadServe service's).
    pub fn new(manager: Arc<SessionManager>, stopping: watch::Receiver<bool>) -> EnvironmentService {
        EnvironmentService { manager, worlds: SharedWorlds::default(), stopping }
    }
}

type ProcessStream = std::pin::Pin<Box<dyn Stream<Item = std::result::Result<dm::EnvironmentResponse, Status>> + Send>>;

#[tonic::async_trait]
impl dm::environment_server::Environment for EnvironmentService {
    type ProcessStream = ProcessStream;

    async fn process(
        &self,
        request: Request<Streaming<dm::EnvironmentRequest>>,
    ) -> std::result::Result<Response<ProcessStream>, Status> {
        let caller = caller(&request)?;
        let mut inbound = request.into_inner();
        let (sender, receiver) = mpsc::channel(STREAM_BUFFER);
        let stopping = self.stopping.clone();
        let mut connection = Connection { service: self.clone(), caller, joined: None };
        tokio::spawn(async move {
            while let Some(message) = next_or_stop(&mut inbound, &stopping, &sender).await {
                let request = match message {
                    Ok(request) => request,
                    // Bytes that are no EnvironmentRequest: the stream cannot go on.
                    Err(status) => {
                        let _ = sender.send(Err(status)).await;
                        break;
                    }
                };
                let payload = connection.handle(request).await.unwrap_or_else(|error| Outbound::Error(in_band(error)));
                if !send_or_stop(&sender, dm::EnvironmentResponse { payload: Some(payload) }, &stopping).await {
                    break;
                }
            }
            // Dropping the connection leaves its world.
            debug!("dm_env_rpc stream ended");
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(receiver))))
    }
}

/// An error as the protocol carries it: a google.rpc.Status in the response, the code radserve's
/// own API would answer with.
fn in_band(error: ServiceError) -> rpc::Status {
    let status = Status::from(error);
    rpc::Status { code: status.code() as i32, message: status.message().to_string(), details: Vec::new() }
}

fn bad(message: impl Into<String>) -> ServiceError {
    ServiceError::BadRequest(message.into())
}

fn not_joined(what: &str) -> ServiceError {
    ServiceError::FailedPrecondition(format!("{what} needs a joined world: send JoinWorldRequest first"))
}

/// What the next Step of a joined stream does.
enum Next {
    /// Just joined: return the env's current observation (a world never reset is reset first).
    Join,
    /// Start a new episode in the stream's env (seeded, if given) and return its first observation.
    Reset { seed: Option<u64> },
    /// Return this first observation of an episode already begun (after an episode's end).
    First(Vec<u8>),
    /// Step the env with the request's action.
    Running,
}

struct Joined {
    world: String,
    env: usize,
    num_envs: usize,
    action: Space,
    observation: Space,
    specs: dm::ActionObservationSpecs,
    next: Next,
    /// The world's ResetWorld count when this stream last looked.
    resets_seen: u64,
    _seat: Seat,
    /// The session is not reaped while a stream is joined to it.
    _lease: LeaseHold,
}

struct Connection {
    service: EnvironmentService,
    caller: Principal,
    joined: Option<Joined>,
}

impl Connection {
    async fn handle(&mut self, request: dm::EnvironmentRequest) -> Result<Outbound> {
        Ok(match request.payload {
            Some(Inbound::CreateWorld(request)) => Outbound::CreateWorld(self.create_world(request).await?),
            Some(Inbound::JoinWorld(request)) => Outbound::JoinWorld(self.join_world(request).await?),
            Some(Inbound::Step(request)) => Outbound::Step(self.step(request).await?),
            Some(Inbound::Reset(request)) => Outbound::Reset(self.reset(request)?),
            Some(Inbound::ResetWorld(request)) => Outbound::ResetWorld(self.reset_world(request).await?),
            Some(Inbound::LeaveWorld(_)) => {
                self.joined = None;
                Outbound::LeaveWorld(dm::LeaveWorldResponse {})
            }
            Some(Inbound::DestroyWorld(request)) => Outbound::DestroyWorld(self.destroy_world(request).await?),
            Some(Inbound::Extension(extension)) => {
                return Err(ServiceError::Transport(Status::unimplemented(format!(
                    "radserve serves no dm_env_rpc extension (got {})",
                    radserve_core::bounds::clip(&extension.type_url)
                ))))
            }
            None => return Err(bad("the EnvironmentRequest holds no request (its payload is empty)")),
        })
    }

    async fn create_world(&mut self, request: dm::CreateWorldRequest) -> Result<dm::CreateWorldResponse> {
        check_count("CreateWorld settings", request.settings.len(), MAX_ENTRIES)?;
        let mut env_id = None;
        let (mut seed, mut num_envs) = (0u64, 1usize);
        let mut options = Options::new();
        for (name, tensor) in &request.settings {
            check_len("a setting name", name, MAX_OPTION_NAME_BYTES)?;
            let value = setting(name, tensor)?;
            match name.as_str() {
                "env_id" => match value {
                    OptionValue::Str(id) => env_id = Some(id),
                    other @ (OptionValue::Bool(_) | OptionValue::Int(_) | OptionValue::Float(_)) => {
                        return Err(bad(format!("setting env_id must be a string (e.g. \"gym/CartPole-v1\"), got {other:?}")))
                    }
                },
                "seed" => seed = non_negative("seed", &value, MAX_SEED)?,
                "num_envs" => num_envs = non_negative("num_envs", &value, u32::MAX as u64)? as usize,
                _ => {
                    options.insert(name.clone(), value);
                }
            }
        }
        let env_id = env_id.ok_or_else(|| {
            bad(format!(
                "CreateWorld needs the setting env_id (a string, e.g. \"gym/CartPole-v1\"); got settings {:?}",
                request.settings.keys().collect::<Vec<_>>()
            ))
        })?;
        check_len("env_id", &env_id, MAX_ID_BYTES)?;
        let info = self
            .service
            .manager
            .create_session(&self.caller, &env_id, num_envs, seed, &options, &SessionExtras { buffer: None, observation_view: None })
            .await?;
        Ok(dm::CreateWorldResponse { world_name: info.session_id })
    }

    async fn join_world(&mut self, request: dm::JoinWorldRequest) -> Result<dm::JoinWorldResponse> {
        if let Some(joined) = &self.joined {
            return Err(ServiceError::FailedPrecondition(format!(
                "this stream already joined world {} (env {}); send LeaveWorldRequest before joining again",
                joined.world, joined.env
            )));
        }
        check_len("world_name", &request.world_name, MAX_ID_BYTES)?;
        check_count("JoinWorld settings", request.settings.len(), MAX_ENTRIES)?;
        let mut env = 0usize;
        for (name, tensor) in &request.settings {
            match name.as_str() {
                "env_index" => env = non_negative("env_index", &setting(name, tensor)?, u32::MAX as u64)? as usize,
                _ => {
                    return Err(bad(format!(
                        "unknown JoinWorld setting '{}': the only one is env_index (which env of the world this stream acts in)",
                        radserve_core::bounds::clip(name)
                    )))
                }
            }
        }
        let manager = &self.service.manager;
        let info = manager.describe(&self.caller, &request.world_name).await?;
        if env >= info.num_envs {
            return Err(bad(format!("env_index {env} is out of range: world {} has {} envs", info.session_id, info.num_envs)));
        }
        let lease = manager.hold(&self.caller, &info.session_id)?;
        let resets_seen = {
            let mut worlds = self.service.worlds.lock().expect("worlds lock");
            let world = worlds.joined.entry(info.session_id.clone()).or_default();
            if !world.seats.insert(env) {
                return Err(ServiceError::FailedPrecondition(format!(
                    "env {env} of world {} is joined by another stream; join another env_index or leave it there first",
                    info.session_id
                )));
            }
            world.resets
        };
        let seat = Seat { worlds: self.service.worlds.clone(), world: info.session_id.clone(), env };
        let specs = specs(&info.action_space, &info.observation_space);
        self.joined = Some(Joined {
            world: info.session_id,
            env,
            num_envs: info.num_envs,
            action: info.action_space,
            observation: info.observation_space,
            specs: specs.clone(),
            next: Next::Join,
            resets_seen,
            _seat: seat,
            _lease: lease,
        });
        Ok(dm::JoinWorldResponse { specs: Some(specs) })
    }

    fn reset(&mut self, request: dm::ResetRequest) -> Result<dm::ResetResponse> {
        let joined = self.joined.as_mut().ok_or_else(|| not_joined("Reset"))?;
        let seed = seed_setting(&request.settings, "Reset")?;
        joined.next = Next::Reset { seed };
        Ok(dm::ResetResponse { specs: Some(joined.specs.clone()) })
    }

    async fn reset_world(&mut self, request: dm::ResetWorldRequest) -> Result<dm::ResetWorldResponse> {
        check_len("world_name", &request.world_name, MAX_ID_BYTES)?;
        let seed = seed_setting(&request.settings, "ResetWorld")?;
        let session = self.service.manager.get(&self.caller, &request.world_name)?;
        session.lock().await.reset_with(&ResetSpec { seed, ..ResetSpec::default() }).await?;
        let mut worlds = self.service.worlds.lock().expect("worlds lock");
        if let Some(world) = worlds.joined.get_mut(&request.world_name) {
            world.resets += 1;
        }
        Ok(dm::ResetWorldResponse {})
    }

    async fn destroy_world(&mut self, request: dm::DestroyWorldRequest) -> Result<dm::DestroyWorldResponse> {
        check_len("world_name", &request.world_name, MAX_ID_BYTES)?;
        let manager = &self.service.manager;
        // Unknown (or another principal's) worlds answer NOT_FOUND before anything else.
        manager.get(&self.caller, &request.world_name)?;
        if let Some(world) = self.service.worlds.lock().expect("worlds lock").joined.get(&request.world_name) {
            return Err(ServiceError::FailedPrecondition(format!(
                "world {} has joined streams (envs {:?}); they must leave it before it is destroyed",
                request.world_name, world.seats
            )));
        }
        manager.close_session(&self.caller, &request.world_name).await?;
        Ok(dm::DestroyWorldResponse {})
    }

    async fn step(&mut self, request: dm::StepRequest) -> Result<dm::StepResponse> {
        let joined = self.joined.as_mut().ok_or_else(|| not_joined("Step"))?;
        check_count("requested_observations", request.requested_observations.len(), MAX_ENTRIES)?;
        check_count("actions", request.actions.len(), MAX_ENTRIES)?;
        let mut requested = BTreeSet::new();
        for &uid in &request.requested_observations {
            if uid != OBSERVATION_UID && uid != REWARD_UID {
                return Err(bad(format!(
                    "no observation has uid {uid}: this world's are {OBSERVATION_UID} ({OBSERVATION_NAME}) and {REWARD_UID} ({REWARD_NAME})"
                )));
            }
            requested.insert(uid);
        }
        let resets = self.service.worlds.lock().expect("worlds lock").joined.get(&joined.world).map_or(0, |world| world.resets);
        let session = self.service.manager.get(&self.caller, &joined.world)?;
        let mut session = session.lock().await;
        if resets != joined.resets_seen {
            joined.resets_seen = resets;
            if let Some(observations) = session.observations() {
                joined.next = Next::First(env_row(&observations, joined.env, joined.num_envs).to_vec());
            }
        }
        let (state, observation, reward) = match std::mem::replace(&mut joined.next, Next::Running) {
            Next::Join => match current(&mut session, joined.env, joined.num_envs).await {
                Ok(observation) => (dm::EnvironmentStateType::Running, observation, 0.0),
                Err(error) => {
                    joined.next = Next::Join;
                    return Err(error);
                }
            },
            Next::Reset { seed } => match reset_env(&mut session, joined.env, joined.num_envs, seed).await {
                Ok(observation) => (dm::EnvironmentStateType::Running, observation, 0.0),
                Err(error) => {
                    joined.next = Next::Reset { seed };
                    return Err(error);
                }
            },
            Next::First(observation) => (dm::EnvironmentStateType::Running, observation, 0.0),
            Next::Running => {
                let action = action_bytes(&request.actions, &joined.action)?;
                // Every env gets the same (valid) action; all but this stream's are skipped.
                let actions = action.repeat(joined.num_envs);
                let mut shape = vec![joined.num_envs];
                shape.extend_from_slice(joined.action.shape());
                let skip: Vec<bool> = (0..joined.num_envs).map(|env| env != joined.env).collect();
                let outcome = match session.step_except(joined.action.dtype(), &shape, &actions, Some(&skip)).await {
                    Ok(outcome) => outcome,
                    Err(error) => {
                        // A failed step leaves the session to be reset: this env starts over.
                        joined.next = Next::Reset { seed: None };
                        return Err(error.into());
                    }
                };
                let env = joined.env;
                let reward = outcome.rewards[env];
                let row = env_row(&outcome.obs, env, joined.num_envs).to_vec();
                match outcome.episodes.iter().position(|episode| episode.env_index == env) {
                    Some(position) => {
                        let ended = &outcome.episodes[position];
                        let state = if ended.terminated {
                            dm::EnvironmentStateType::Terminated
                        } else {
                            dm::EnvironmentStateType::Interrupted
                        };
                        let last = env_row(&outcome.final_obs, position, outcome.episodes.len()).to_vec();
                        joined.next = Next::First(row);
                        (state, last, reward)
                    }
                    None => (dm::EnvironmentStateType::Running, row, reward),
                }
            }
        };
        let mut observations = HashMap::new();
        if requested.contains(&OBSERVATION_UID) {
            observations.insert(OBSERVATION_UID, tensor(&joined.observation, observation));
        }
        if requested.contains(&REWARD_UID) {
            observations.insert(
                REWARD_UID,
                dm::Tensor { payload: Some(TensorPayload::Doubles(dm::tensor::DoubleArray { array: vec![reward] })), shape: vec![] },
            );
        }
        Ok(dm::StepResponse { state: state as i32, observations })
    }
}

/// Env `env`'s current observation; a world never reset (or whose last step failed) is reset
/// whole first, env i seeded `seed + i` from its creation as a session's first reset is.
async fn current(session: &mut Session, env: usize, num_envs: usize) -> Result<Vec<u8>> {
    if session.needs_reset() {
        session.reset_with(&ResetSpec::default()).await?;
    }
    let observations = session.observations().ok_or_else(|| ServiceError::Internal("a session just reset has no observations".into()))?;
    Ok(env_row(&observations, env, num_envs).to_vec())
}

/// Starts a new episode in env `env` and returns its first observation. Seeded: reset with that
/// seed. Unseeded, an env that has not stepped since its last reset is already at an episode's
/// start and stays there (so a world's first episodes are its seed's, whether or not the client
/// sends Reset before its first step); otherwise its random stream continues.
async fn reset_env(session: &mut Session, env: usize, num_envs: usize, seed: Option<u64>) -> Result<Vec<u8>> {
    let fresh = session.needs_reset() || session.episode_lengths()[env] == 0;
    if seed.is_none() && fresh {
        return current(session, env, num_envs).await;
    }
    if session.needs_reset() {
        session.reset_with(&ResetSpec::default()).await?;
    }
    let mut mask = vec![false; num_envs];
    mask[env] = true;
    let env_seeds = seed.map(|seed| vec![seed; num_envs]);
    let observations = session.reset_with(&ResetSpec { seed: None, env_seeds, mask: Some(mask) }).await?;
    Ok(env_row(&observations, env, num_envs).to_vec())
}

/// Row `index` of `rows` equal rows.
fn env_row(data: &[u8], index: usize, rows: usize) -> &[u8] {
    let len = data.len() / rows.max(1);
    &data[index * len..(index + 1) * len]
}

/// A setting's single value.
fn setting(name: &str, tensor: &dm::Tensor) -> Result<OptionValue> {
    let clipped = radserve_core::bounds::clip(name);
    // The one element of a scalar tensor (shape [] or all ones).
    let only = |count: usize| {
        let elements: i64 = tensor.shape.iter().map(|&d| i64::from(d)).product();
        if count != 1 || elements != 1 {
            return Err(bad(format!("setting '{clipped}' must be a single value (a scalar tensor); it holds {count}")));
        }
        Ok(0)
    };
    Ok(match &tensor.payload {
        Some(TensorPayload::Strings(array)) => {
            let text = &array.array[only(array.array.len())?];
            check_len(&format!("setting '{clipped}'"), text, MAX_OPTION_TEXT_BYTES)?;
            OptionValue::Str(text.clone())
        }
        Some(TensorPayload::Bools(array)) => OptionValue::Bool(array.array[only(array.array.len())?]),
        Some(TensorPayload::Int32s(array)) => OptionValue::Int(array.array[only(array.array.len())?].into()),
        Some(TensorPayload::Int64s(array)) => OptionValue::Int(array.array[only(array.array.len())?]),
        Some(TensorPayload::Uint32s(array)) => OptionValue::Int(array.array[only(array.array.len())?].into()),
        Some(TensorPayload::Uint64s(array)) => OptionValue::Int(
            i64::try_from(array.array[only(array.array.len())?]).map_err(|_| bad(format!("setting '{clipped}' is too large")))?,
        ),
        Some(TensorPayload::Uint8s(array)) => OptionValue::Int(array.array[only(array.array.len())?].into()),
        Some(TensorPayload::Int8s(array)) => OptionValue::Int(i64::from(array.array[only(array.array.len())?] as i8)),
        Some(TensorPayload::Floats(array)) => OptionValue::Float(array.array[only(array.array.len())?].into()),
        Some(TensorPayload::Doubles(array)) => OptionValue::Float(array.array[only(array.array.len())?]),
        Some(TensorPayload::Protos(_)) | None => {
            return Err(bad(format!("setting '{clipped}' must hold a number, a bool or a string")));
        }
    })
}

/// An integer setting in `[0, max]`.
fn non_negative(name: &str, value: &OptionValue, max: u64) -> Result<u64> {
    match value {
        OptionValue::Int(value) if *value >= 0 && (*value as u64) <= max => Ok(*value as u64),
        other @ (OptionValue::Bool(_) | OptionValue::Int(_) | OptionValue::Float(_) | OptionValue::Str(_)) => {
            Err(bad(format!("setting {name} must be an integer in [0, {max}], got {other:?}")))
        }
    }
}

/// The optional `seed` setting of Reset and ResetWorld; any other setting is refused.
fn seed_setting(settings: &HashMap<String, dm::Tensor>, what: &str) -> Result<Option<u64>> {
    check_count(&format!("{what} settings"), settings.len(), MAX_ENTRIES)?;
    let mut seed = None;
    for (name, tensor) in settings {
        if name != "seed" {
            return Err(bad(format!(
                "unknown {what} setting '{}': the only one is seed (an integer)",
                radserve_core::bounds::clip(name)
            )));
        }
        seed = Some(non_negative("seed", &setting(name, tensor)?, MAX_SEED)?);
    }
    Ok(seed)
}

/// The element type of a tensor's payload as radserve's, its values as little-endian bytes and its
/// element count; None for payloads no radserve space holds.
fn payload_bytes(payload: &TensorPayload) -> Option<(DType, Vec<u8>, usize)> {
    fn bytes<T: Copy, const N: usize>(values: &[T], to: fn(T) -> [u8; N]) -> Vec<u8> {
        values.iter().flat_map(|&value| to(value)).collect()
    }
    Some(match payload {
        TensorPayload::Floats(array) => (DType::Float32, bytes(&array.array, f32::to_le_bytes), array.array.len()),
        TensorPayload::Doubles(array) => (DType::Float64, bytes(&array.array, f64::to_le_bytes), array.array.len()),
        TensorPayload::Int32s(array) => (DType::Int32, bytes(&array.array, i32::to_le_bytes), array.array.len()),
        TensorPayload::Int64s(array) => (DType::Int64, bytes(&array.array, i64::to_le_bytes), array.array.len()),
        TensorPayload::Uint8s(array) => (DType::Uint8, array.array.clone(), array.array.len()),
        TensorPayload::Bools(array) => (DType::Bool, array.array.iter().map(|&b| u8::from(b)).collect(), array.array.len()),
        TensorPayload::Int8s(_)
        | TensorPayload::Uint32s(_)
        | TensorPayload::Uint64s(_)
        | TensorPayload::Strings(_)
        | TensorPayload::Protos(_) => return None,
    })
}

fn data_type_name(dtype: DType) -> &'static str {
    match dtype {
        DType::Float32 => "FLOAT",
        DType::Float64 => "DOUBLE",
        DType::Int32 => "INT32",
        DType::Int64 => "INT64",
        DType::Uint8 => "UINT8",
        DType::Bool => "BOOL",
    }
}

/// The shape a tensor of `count` elements has: its own with a variable (negative) dimension
/// inferred, the way dm_env_rpc's `tensor_utils.unpack_tensor` reads it (at most one variable
/// dimension; a single element broadcasts to the whole shape; no shape and several elements: 1-D).
fn resolved_shape(shape: &[i32], count: usize) -> std::result::Result<Vec<usize>, String> {
    if shape.is_empty() {
        return Ok(if count == 1 { Vec::new() } else { vec![count] });
    }
    if shape.len() > 32 {
        return Err(format!("a shape of {} dimensions", shape.len()));
    }
    let variable: Vec<usize> = (0..shape.len()).filter(|&axis| shape[axis] < 0).collect();
    if variable.len() > 1 {
        return Err(format!("shape {shape:?} has {} variable dimensions; at most one may be negative", variable.len()));
    }
    let known: usize = shape.iter().filter(|&&dim| dim >= 0).map(|&dim| dim as usize).product();
    let mut resolved: Vec<usize> = shape.iter().map(|&dim| dim.max(0) as usize).collect();
    match variable.first() {
        Some(&axis) => {
            if known == 0 || !count.is_multiple_of(known) {
                return Err(format!("{count} elements do not fill shape {shape:?}"));
            }
            resolved[axis] = count / known;
        }
        None if count == known || count == 1 => {}
        None => return Err(format!("shape {shape:?} holds {known} elements but the payload has {count}")),
    }
    Ok(resolved)
}

/// The action of a Step request as one env's action bytes, checked against the world's action
/// space (its dtype exactly, its shape, its bounds: the core checks them again).
fn action_bytes(actions: &HashMap<u64, dm::Tensor>, space: &Space) -> Result<Vec<u8>> {
    let expected = || format!("{} {ACTION_NAME} (uid {ACTION_UID}) {}", data_type_name(space.dtype()), space.describe());
    if let Some(uid) = actions.keys().find(|&&uid| uid != ACTION_UID) {
        return Err(bad(format!("no action has uid {uid}: this world's one action is {}", expected())));
    }
    let tensor = actions.get(&ACTION_UID).ok_or_else(|| bad(format!("the step has no action; it needs {}", expected())))?;
    let payload = tensor.payload.as_ref().ok_or_else(|| bad(format!("the action tensor is empty; it must be {}", expected())))?;
    let Some((dtype, data, count)) = payload_bytes(payload).filter(|(dtype, _, _)| *dtype == space.dtype()) else {
        return Err(bad(format!("the action's payload type does not match its spec: it must be {}", expected())));
    };
    let shape = resolved_shape(&tensor.shape, count).map_err(|problem| bad(format!("action: {problem}; it must be {}", expected())))?;
    if shape != space.shape() {
        return Err(bad(format!("an action of shape {shape:?}; it must be {}", expected())));
    }
    let elements = space.num_elements().max(1);
    let data = if count == 1 && elements > 1 { data.repeat(elements) } else { data };
    validate_actions(space, 1, dtype, &{
        let mut batch = vec![1];
        batch.extend_from_slice(space.shape());
        batch
    }, &data)?;
    Ok(data)
}

/// An observation row as a Tensor of its space's type and shape.
fn tensor(space: &Space, data: Vec<u8>) -> dm::Tensor {
    fn values<T, const N: usize>(data: &[u8], from: fn([u8; N]) -> T) -> Vec<T> {
        data.chunks_exact(N).map(|chunk| from(chunk.try_into().expect("N bytes"))).collect()
    }
    let payload = match space.dtype() {
        DType::Uint8 => TensorPayload::Uint8s(dm::tensor::Uint8Array { array: data }),
        DType::Bool => TensorPayload::Bools(dm::tensor::BoolArray { array: data.iter().map(|&b| b != 0).collect() }),
        DType::Float32 => TensorPayload::Floats(dm::tensor::FloatArray { array: values(&data, f32::from_le_bytes) }),
        DType::Float64 => TensorPayload::Doubles(dm::tensor::DoubleArray { array: values(&data, f64::from_le_bytes) }),
        DType::Int32 => TensorPayload::Int32s(dm::tensor::Int32Array { array: values(&data, i32::from_le_bytes) }),
        DType::Int64 => TensorPayload::Int64s(dm::tensor::Int64Array { array: values(&data, i64::from_le_bytes) }),
    };
    dm::Tensor { payload: Some(payload), shape: space.shape().iter().map(|&dim| dim as i32).collect() }
}

fn data_type(dtype: DType) -> dm::DataType {
    match dtype {
        DType::Uint8 => dm::DataType::Uint8,
        DType::Bool => dm::DataType::Bool,
        DType::Float32 => dm::DataType::Float,
        DType::Float64 => dm::DataType::Double,
        DType::Int32 => dm::DataType::Int32,
        DType::Int64 => dm::DataType::Int64,
    }
}

/// A bound in the spec's own element type: one value for every element, or one per element.
fn bound(dtype: DType, values: &[f64]) -> Option<dm::tensor_spec::Value> {
    if values.is_empty() || values.iter().all(|value| value.is_infinite()) {
        return None;
    }
    let payload = match dtype {
        DType::Float32 => BoundPayload::Floats(dm::tensor::FloatArray { array: values.iter().map(|&v| v as f32).collect() }),
        DType::Float64 => BoundPayload::Doubles(dm::tensor::DoubleArray { array: values.to_vec() }),
        DType::Int32 => BoundPayload::Int32s(dm::tensor::Int32Array { array: values.iter().map(|&v| v as i32).collect() }),
        DType::Int64 => BoundPayload::Int64s(dm::tensor::Int64Array { array: values.iter().map(|&v| v as i64).collect() }),
        DType::Uint8 => BoundPayload::Uint8s(dm::tensor::Uint8Array { array: values.iter().map(|&v| v as u8).collect() }),
        // Not a number to dm_env_rpc: no bounds.
        DType::Bool => return None,
    };
    Some(dm::tensor_spec::Value { payload: Some(payload) })
}

fn tensor_spec(name: &str, space: &Space) -> dm::TensorSpec {
    let (min, max) = match space {
        Space::Box { dtype, low, high, .. } => (bound(*dtype, low), bound(*dtype, high)),
        Space::Discrete { n } => (bound(DType::Int64, &[0.0]), bound(DType::Int64, &[(*n - 1) as f64])),
    };
    dm::TensorSpec {
        name: name.to_string(),
        shape: space.shape().iter().map(|&dim| dim as i32).collect(),
        dtype: data_type(space.dtype()) as i32,
        min,
        max,
    }
}

/// Every world's specs: its action, its observation and its reward.
fn specs(action: &Space, observation: &Space) -> dm::ActionObservationSpecs {
    let reward = dm::TensorSpec { name: REWARD_NAME.into(), shape: vec![], dtype: dm::DataType::Double as i32, min: None, max: None };
    dm::ActionObservationSpecs {
        actions: HashMap::from([(ACTION_UID, tensor_spec(ACTION_NAME, action))]),
        observations: HashMap::from([(OBSERVATION_UID, tensor_spec(OBSERVATION_NAME, observation)), (REWARD_UID, reward)]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_resolve_as_dm_env_rpc_reads_them() {
        assert_eq!(resolved_shape(&[], 1).unwrap(), Vec::<usize>::new());
        assert_eq!(resolved_shape(&[], 3).unwrap(), vec![3]);
        assert_eq!(resolved_shape(&[2, 3], 6).unwrap(), vec![2, 3]);
        assert_eq!(resolved_shape(&[-1, 3], 6).unwrap(), vec![2, 3]);
        assert_eq!(resolved_shape(&[2, 3], 1).unwrap(), vec![2, 3], "one element broadcasts");
        assert!(resolved_shape(&[-1, -1], 6).is_err());
        assert!(resolved_shape(&[-1, 4], 6).is_err());
        assert!(resolved_shape(&[2, 3], 5).is_err());
        assert!(resolved_shape(&[0, -1], 0).is_err());
    }

    fn action(payload: TensorPayload, shape: Vec<i32>) -> HashMap<u64, dm::Tensor> {
        HashMap::from([(ACTION_UID, dm::Tensor { payload: Some(payload), shape })])
    }

    #[test]
    fn actions_must_match_the_spec_exactly() {
        let space = Space::Box { dtype: DType::Float32, shape: vec![2], low: vec![-1.0], high: vec![1.0] };
        let floats = |values: Vec<f32>| TensorPayload::Floats(dm::tensor::FloatArray { array: values });
        let ok = action_bytes(&action(floats(vec![0.5, -0.5]), vec![2]), &space).unwrap();
        assert_eq!(ok, [0.5f32.to_le_bytes(), (-0.5f32).to_le_bytes()].concat());
        assert_eq!(action_bytes(&action(floats(vec![0.25]), vec![2]), &space).unwrap().len(), 8, "broadcast");
        let doubles = TensorPayload::Doubles(dm::tensor::DoubleArray { array: vec![0.0, 0.0] });
        assert!(action_bytes(&action(doubles, vec![2]), &space).unwrap_err().to_string().contains("FLOAT action"));
        assert!(action_bytes(&action(floats(vec![2.0, 0.0]), vec![2]), &space).unwrap_err().to_string().contains("outside"));
        assert!(action_bytes(&action(floats(vec![0.0, 0.0]), vec![2, 1]), &space).is_err());
        let mut two = action(floats(vec![0.0, 0.0]), vec![2]);
        two.insert(7, dm::Tensor::default());
        assert!(action_bytes(&two, &space).unwrap_err().to_string().contains("uid 7"));
        assert!(action_bytes(&HashMap::new(), &space).unwrap_err().to_string().contains("no action"));
        let discrete = Space::Discrete { n: 2 };
        let ints = |value| TensorPayload::Int64s(dm::tensor::Int64Array { array: vec![value] });
        assert_eq!(action_bytes(&action(ints(1), vec![]), &discrete).unwrap(), 1i64.to_le_bytes());
        assert!(action_bytes(&action(ints(2), vec![]), &discrete).is_err());
        assert!(action_bytes(&action(ints(i64::MIN), vec![]), &discrete).is_err());
    }

    #[test]
    fn specs_carry_bounds_in_the_spec_type() {
        let state = Space::Box { dtype: DType::Float64, shape: vec![3], low: vec![f64::NEG_INFINITY], high: vec![f64::INFINITY] };
        let specs = specs(&Space::Discrete { n: 4 }, &state);
        let action = &specs.actions[&ACTION_UID];
        assert_eq!((action.dtype, action.shape.as_slice()), (dm::DataType::Int64 as i32, &[][..]));
        assert_eq!(action.max.as_ref().unwrap().payload, Some(BoundPayload::Int64s(dm::tensor::Int64Array { array: vec![3] })));
        let observation = &specs.observations[&OBSERVATION_UID];
        assert!(observation.min.is_none() && observation.max.is_none(), "infinite bounds are left out");
        assert_eq!(specs.observations[&REWARD_UID].dtype, dm::DataType::Double as i32);
    }
}
