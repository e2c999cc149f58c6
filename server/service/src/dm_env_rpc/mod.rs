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
use std::sync::Arc;

use radserve_core::bounds::{check_count, MAX_OPTIONS};
use radserve_core::session::Session;
use radserve_core::{LeaseHold, Principal, SessionManager, Space};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use tracing::debug;

use crate::auth::caller;
use crate::error::{Result, ServiceError};
use crate::pb::dm_env_rpc::v1 as dm;
use crate::pb::google::rpc as rpc;
use crate::streams::{pump, Source};
use dm::environment_request::Payload as Inbound;
use dm::environment_response::Payload as Outbound;
use dm::tensor::Payload as TensorPayload;

mod tensors;
mod worlds;

use tensors::{action_bytes, seed_setting, tensor};
use worlds::{Seat, SharedWorlds};

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
        let connection = Connection { service: self.clone(), caller: caller(&request)?, joined: None };
        let source = Requests { connection, inbound: request.into_inner() };
        let (sender, receiver) = mpsc::channel(STREAM_BUFFER);
        let stopping = self.stopping.clone();
        tokio::spawn(async move {
            // Dropping the connection (with the source) leaves its world.
            let ended = pump(source, &sender, &stopping).await;
            debug!(?ended, "dm_env_rpc stream ended");
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(receiver))))
    }
}

/// A Process stream: each request answered in order, errors in-band; bytes that are no
/// EnvironmentRequest end the stream with their status.
struct Requests {
    connection: Connection,
    inbound: Streaming<dm::EnvironmentRequest>,
}

impl Source for Requests {
    type Input = dm::EnvironmentRequest;
    type Message = dm::EnvironmentResponse;

    async fn next(&mut self) -> Option<std::result::Result<dm::EnvironmentRequest, Status>> {
        self.inbound.next().await
    }

    async fn make(&mut self, request: dm::EnvironmentRequest) -> std::result::Result<dm::EnvironmentResponse, Status> {
        let payload = self.connection.handle(request).await.unwrap_or_else(|error| Outbound::Error(in_band(error)));
        Ok(dm::EnvironmentResponse { payload: Some(payload) })
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
                return Err(ServiceError::Unimplemented(format!(
                    "radserve serves no dm_env_rpc extension (got {})",
                    radserve_core::bounds::clip(&extension.type_url)
                )))
            }
            None => return Err(bad("the EnvironmentRequest holds no request (its payload is empty)")),
        })
    }

    fn reset(&mut self, request: dm::ResetRequest) -> Result<dm::ResetResponse> {
        let joined = self.joined.as_mut().ok_or_else(|| not_joined("Reset"))?;
        let seed = seed_setting(&request.settings, "Reset")?;
        joined.next = Next::Reset { seed };
        Ok(dm::ResetResponse { specs: Some(joined.specs.clone()) })
    }

    async fn step(&mut self, request: dm::StepRequest) -> Result<dm::StepResponse> {
        let joined = self.joined.as_mut().ok_or_else(|| not_joined("Step"))?;
        let requested = requested_observations(&request.requested_observations)?;
        check_count("actions", request.actions.len(), MAX_ENTRIES)?;
        let resets = self.service.worlds.lock().expect("worlds lock").joined.get(&joined.world).map_or(0, |world| world.resets);
        let session = self.service.manager.get(&self.caller, &joined.world)?;
        let mut session = session.lock().await;
        if resets != joined.resets_seen {
            joined.resets_seen = resets;
            if let Some(observation) = session.env_observation(joined.env) {
                joined.next = Next::First(observation);
            }
        }
        let (state, observation, reward) = joined.advance(&mut session, &request.actions).await?;
        let mut observations = HashMap::new();
        if requested.contains(&OBSERVATION_UID) {
            observations.insert(OBSERVATION_UID, tensor(&joined.observation, observation));
        }
        if requested.contains(&REWARD_UID) {
            let reward = TensorPayload::Doubles(dm::tensor::DoubleArray { array: vec![reward] });
            observations.insert(REWARD_UID, dm::Tensor { payload: Some(reward), shape: vec![] });
        }
        Ok(dm::StepResponse { state: state as i32, observations })
    }
}

impl Joined {
    /// What this stream's Step does next (`next`), done in the session: the state, observation and
    /// reward it answers. A failure leaves `next` where a retry starts again.
    async fn advance(
        &mut self,
        session: &mut Session,
        actions: &HashMap<u64, dm::Tensor>,
    ) -> Result<(dm::EnvironmentStateType, Vec<u8>, f64)> {
        let running = |observation| (dm::EnvironmentStateType::Running, observation, 0.0);
        match std::mem::replace(&mut self.next, Next::Running) {
            Next::Join => session.current_env_observation(self.env).await.map(running).map_err(|error| {
                self.next = Next::Join;
                error.into()
            }),
            Next::Reset { seed } => session.reset_env(self.env, seed).await.map(running).map_err(|error| {
                self.next = Next::Reset { seed };
                error.into()
            }),
            Next::First(observation) => Ok(running(observation)),
            Next::Running => {
                let action = action_bytes(actions, &self.action)?;
                let step = session.step_env(self.env, &action).await.map_err(|error| {
                    // A failed step leaves the session to be reset: this env starts over.
                    self.next = Next::Reset { seed: None };
                    ServiceError::from(error)
                })?;
                Ok(match step.ended {
                    Some(end) => {
                        self.next = Next::First(step.observation);
                        let state =
                            if end.terminated { dm::EnvironmentStateType::Terminated } else { dm::EnvironmentStateType::Interrupted };
                        (state, end.last_observation, step.reward)
                    }
                    None => (dm::EnvironmentStateType::Running, step.observation, step.reward),
                })
            }
        }
    }
}

/// The uids a Step asks to observe, each one this world has.
fn requested_observations(uids: &[u64]) -> Result<BTreeSet<u64>> {
    check_count("requested_observations", uids.len(), MAX_ENTRIES)?;
    uids.iter()
        .map(|&uid| {
            if uid != OBSERVATION_UID && uid != REWARD_UID {
                return Err(bad(format!(
                    "no observation has uid {uid}: this world's are {OBSERVATION_UID} ({OBSERVATION_NAME}) and {REWARD_UID} ({REWARD_NAME})"
                )));
            }
            Ok(uid)
        })
        .collect()
}
