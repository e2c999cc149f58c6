//! radserve's own API (`radserve.v1.RadServe`): each handler checks and converts its request, calls
//! the core, and maps the core's errors to statuses (`crate::error`). The sample streams live in
//! `sample_streams`, the shared-stepping channel in `acting`, what every stream shares in
//! `streams`, client deadlines in `deadline`.

use std::pin::Pin;
use std::sync::Arc;
use std::time::Instant;

use radserve_core::{Principal, SessionExtras, SessionManager};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use tracing::debug;

use crate::shared_stepping::{self, OpenChannels};
use crate::auth::caller;
use crate::convert::{self, observation_tensor};
use crate::deadline::{check_deadline, client_deadline, run_to_end};
use crate::error::{Result as ServiceResult, ServiceError};
use crate::handoff::PeerPolicy;
use crate::proto::{self, act_request, act_response, rad_serve_server::RadServe};
use crate::streams::{pump, Source, StreamStopper};

/// Responses of an `Act` stream that may wait for the client to read them.
const ACT_STREAM_BUFFER: usize = 2;

#[derive(Clone)]
pub struct RadServeService {
    pub(crate) manager: Arc<SessionManager>,
    /// Threads that augment minibatches (never a tokio worker).
    pub(crate) augment_pool: Arc<rayon::ThreadPool>,
    /// Sessions with a shared-stepping channel open.
    stepping_channels: OpenChannels,
    /// Who may receive shared memory on this host.
    pub(crate) peers: PeerPolicy,
    /// Becomes true when the server starts shutting down: every open stream then ends.
    pub(crate) stopping: watch::Receiver<bool>,
}

impl RadServeService {
    /// Turns true when the server begins to shut down (for the other services' streams).
    pub fn stopping(&self) -> watch::Receiver<bool> {
        self.stopping.clone()
    }

    pub fn new(
        manager: Arc<SessionManager>,
        augment_pool: Arc<rayon::ThreadPool>,
        peers: PeerPolicy,
    ) -> (RadServeService, StreamStopper) {
        let (stop, stopping) = watch::channel(false);
        (RadServeService { manager, augment_pool, stepping_channels: OpenChannels::default(), peers, stopping }, StreamStopper(stop))
    }

    /// Resets and steps run to their end in a task of their own, even when the caller stops waiting
    /// (its deadline passed, it left): cut short after the workers got it, a step would leave the envs
    /// a step ahead of the session's stacks and replay. What the deadline can still prevent is
    /// checked once the session is free: a request whose client deadline has passed by then is
    /// answered DEADLINE_EXCEEDED without being sent.
    async fn reset(&self, caller: &Principal, request: proto::ResetRequest, deadline: Option<Instant>) -> ServiceResult<proto::ResetResponse> {
        let session = self.manager.get(caller, &request.session_id)?;
        run_to_end(async move {
            let mut session = session.lock().await;
            check_deadline(deadline, "Reset")?;
            let obs = session.reset_with(&convert::reset_spec(&request)).await?;
            Ok(proto::ResetResponse {
                obs: Some(observation_tensor(&session.observation_space, session.num_envs(), obs)),
                reset_infos: convert::infos_to_proto(session.reset_infos().clone()),
            })
        })
        .await
    }

    async fn step(&self, caller: &Principal, request: proto::StepRequest, deadline: Option<Instant>) -> ServiceResult<proto::StepResponse> {
        let (dtype, shape) = convert::tensor_header(request.actions.as_ref(), "actions")?;
        let actions = request.actions.map(|tensor| tensor.data).unwrap_or_default();
        let skip = request.skip;
        let session = self.manager.get(caller, &request.session_id)?;
        run_to_end(async move {
            let mut session = session.lock().await;
            check_deadline(deadline, "Step")?;
            let skip = (!skip.is_empty()).then_some(skip.as_slice());
            let outcome = session.step_except(dtype, &shape, &actions, skip).await?;
            Ok(convert::step_to_proto(&session.observation_space, outcome))
        })
        .await
    }

    async fn async_reset(&self, caller: &Principal, request: proto::AsyncResetRequest) -> ServiceResult<proto::AsyncResetResponse> {
        let session = self.manager.get(caller, &request.session_id)?;
        run_to_end(async move {
            session.lock().await.async_reset(request.seed).await?;
            Ok(proto::AsyncResetResponse {})
        })
        .await
    }

    async fn send(&self, caller: &Principal, request: proto::SendRequest) -> ServiceResult<proto::SendResponse> {
        let (dtype, shape) = convert::tensor_header(request.actions.as_ref(), "actions")?;
        let actions = request.actions.map(|tensor| tensor.data).unwrap_or_default();
        let env_ids: Vec<u64> = request.env_ids.iter().map(|&env| env as u64).collect();
        let session = self.manager.get(caller, &request.session_id)?;
        run_to_end(async move {
            let mut session = session.lock().await;
            let (rows, shape, sent) = session.scatter_actions(dtype, &shape, &actions, &env_ids)?;
            session.send(dtype, &shape, &rows, &sent).await?;
            Ok(proto::SendResponse {})
        })
        .await
    }

    /// Recv, after a send when the request carries actions: one call per batch.
    async fn recv(&self, caller: &Principal, request: proto::RecvRequest) -> ServiceResult<proto::RecvResponse> {
        let send = match request.actions {
            Some(tensor) => {
                let (dtype, shape) = convert::tensor_header(Some(&tensor), "actions")?;
                Some((dtype, shape, tensor.data, request.env_ids.iter().map(|&env| env as u64).collect::<Vec<_>>()))
            }
            None if request.env_ids.is_empty() => None,
            None => return Err(ServiceError::BadRequest("env_ids without actions: give the actions to send them".into())),
        };
        let session = self.manager.get(caller, &request.session_id)?;
        run_to_end(async move {
            let mut session = session.lock().await;
            let (ready, outcome) = match send {
                Some((dtype, shape, actions, env_ids)) => {
                    let (rows, shape, sent) = session.scatter_actions(dtype, &shape, &actions, &env_ids)?;
                    session.send_recv(dtype, &shape, &rows, &sent).await?
                }
                None => session.recv().await?,
            };
            Ok(convert::recv_to_proto(&session.observation_space, &ready, outcome))
        })
        .await
    }

    async fn act_once(&self, caller: &Principal, request: proto::ActRequest) -> ServiceResult<proto::ActResponse> {
        let response = match request.request {
            Some(act_request::Request::Reset(reset)) => act_response::Response::Reset(self.reset(caller, reset, None).await?),
            Some(act_request::Request::Step(step)) => act_response::Response::Step(self.step(caller, step, None).await?),
            None => return Err(ServiceError::BadRequest("ActRequest must hold a reset or a step".into())),
        };
        Ok(proto::ActResponse { response: Some(response) })
    }
}

type ActStream = Pin<Box<dyn Stream<Item = Result<proto::ActResponse, Status>> + Send>>;
pub(crate) type SampleStream = Pin<Box<dyn Stream<Item = Result<proto::BatchChunk, Status>> + Send>>;
pub(crate) type SharedSampleStream = Pin<Box<dyn Stream<Item = Result<proto::SharedSampleResponse, Status>> + Send>>;

#[tonic::async_trait]
impl RadServe for RadServeService {
    async fn server_info(&self, _request: Request<proto::ServerInfoRequest>) -> Result<Response<proto::ServerInfoResponse>, Status> {
        Ok(Response::new(proto::ServerInfoResponse { version: crate::VERSION.into(), api: crate::API.into() }))
    }

    async fn list_envs(&self, request: Request<proto::ListEnvsRequest>) -> Result<Response<proto::ListEnvsResponse>, Status> {
        let prefix = request.into_inner().prefix;
        radserve_core::bounds::check_len("prefix", &prefix, radserve_core::bounds::MAX_ID_BYTES).map_err(ServiceError::from)?;
        let catalog = self.manager.catalog().await.map_err(ServiceError::from)?;
        let envs = catalog
            .iter()
            .filter(|entry| entry.id.full().starts_with(&prefix))
            .map(convert::catalog_entry_to_proto)
            .collect();
        Ok(Response::new(proto::ListEnvsResponse { envs }))
    }

    async fn create_session(
        &self,
        request: Request<proto::CreateSessionRequest>,
    ) -> Result<Response<proto::SessionInfo>, Status> {
        let caller = caller(&request)?;
        let request = request.into_inner();
        let options = convert::options_from_proto(&request.options)?;
        let info = self
            .manager
            .create_session(
                &caller,
                &request.env_id,
                request.num_envs as usize,
                request.seed,
                &options,
                &SessionExtras {
                    buffer: convert::buffer_request(request.replay.as_ref()),
                    observation_view: (!request.observation_view.is_empty()).then(|| request.observation_view.clone()),
                    name: (!request.name.is_empty()).then(|| request.name.clone()),
                },
            )
            .await
            .map_err(ServiceError::from)?;
        Ok(Response::new(convert::session_info_to_proto(&info)))
    }

    async fn list_sessions(
        &self,
        request: Request<proto::ListSessionsRequest>,
    ) -> Result<Response<proto::ListSessionsResponse>, Status> {
        let sessions = self.manager.list_sessions(&caller(&request)?).iter().map(convert::session_summary_to_proto).collect();
        let idle_timeout_seconds = self.manager.idle_timeout().map_or(0.0, |timeout| timeout.as_secs_f64());
        Ok(Response::new(proto::ListSessionsResponse { sessions, idle_timeout_seconds }))
    }

    async fn describe_session(
        &self,
        request: Request<proto::DescribeSessionRequest>,
    ) -> Result<Response<proto::SessionInfo>, Status> {
        let caller = caller(&request)?;
        let info = self.manager.describe(&caller, &request.into_inner().session_id).await.map_err(ServiceError::from)?;
        Ok(Response::new(convert::session_info_to_proto(&info)))
    }

    async fn close_session(
        &self,
        request: Request<proto::CloseSessionRequest>,
    ) -> Result<Response<proto::CloseSessionResponse>, Status> {
        let caller = caller(&request)?;
        let request = request.into_inner();
        self.manager
            .close_session_with(&caller, &request.session_id, request.discard_snapshot)
            .await
            .map_err(ServiceError::from)?;
        Ok(Response::new(proto::CloseSessionResponse {}))
    }

    async fn reset(&self, request: Request<proto::ResetRequest>) -> Result<Response<proto::ResetResponse>, Status> {
        let (caller, deadline) = (caller(&request)?, client_deadline(&request));
        Ok(Response::new(RadServeService::reset(self, &caller, request.into_inner(), deadline).await?))
    }

    async fn step(&self, request: Request<proto::StepRequest>) -> Result<Response<proto::StepResponse>, Status> {
        let (caller, deadline) = (caller(&request)?, client_deadline(&request));
        Ok(Response::new(RadServeService::step(self, &caller, request.into_inner(), deadline).await?))
    }

    async fn async_reset(
        &self,
        request: Request<proto::AsyncResetRequest>,
    ) -> Result<Response<proto::AsyncResetResponse>, Status> {
        let caller = caller(&request)?;
        Ok(Response::new(RadServeService::async_reset(self, &caller, request.into_inner()).await?))
    }

    async fn send(&self, request: Request<proto::SendRequest>) -> Result<Response<proto::SendResponse>, Status> {
        let caller = caller(&request)?;
        Ok(Response::new(RadServeService::send(self, &caller, request.into_inner()).await?))
    }

    async fn recv(&self, request: Request<proto::RecvRequest>) -> Result<Response<proto::RecvResponse>, Status> {
        let caller = caller(&request)?;
        Ok(Response::new(RadServeService::recv(self, &caller, request.into_inner()).await?))
    }

    type ActStream = ActStream;

    async fn act(&self, request: Request<Streaming<proto::ActRequest>>) -> Result<Response<ActStream>, Status> {
        let source = ActRequests { service: self.clone(), caller: caller(&request)?, inbound: request.into_inner() };
        let (sender, receiver) = mpsc::channel(ACT_STREAM_BUFFER);
        let stopping = self.stopping.clone();
        tokio::spawn(async move {
            let ended = pump(source, &sender, &stopping).await;
            debug!(?ended, "act stream ended");
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(receiver))))
    }

    async fn share_acting(
        &self,
        request: Request<proto::ShareActingRequest>,
    ) -> Result<Response<proto::SharedActingChannel>, Status> {
        let caller = caller(&request)?;
        let session_id = request.into_inner().session_id;
        let (description, channel) =
            shared_stepping::open(self.manager.clone(), caller, &session_id, &self.stepping_channels, self.peers.clone())
                .await
                .map_err(Status::from)?;
        tokio::spawn(channel.serve(session_id));
        Ok(Response::new(description))
    }

    async fn set_policy(&self, request: Request<proto::SetPolicyRequest>) -> Result<Response<proto::SetPolicyResponse>, Status> {
        let caller = caller(&request)?;
        let request = request.into_inner();
        radserve_core::bounds::check_len("session_id", &request.session_id, radserve_core::bounds::MAX_ID_BYTES)
            .map_err(ServiceError::from)?;
        let head = convert::policy_head(request.head, request.noise.as_ref())?;
        let summary = self
            .manager
            .set_policy(&caller, &request.session_id, request.model, head, request.version)
            .await
            .map_err(ServiceError::from)?;
        Ok(Response::new(proto::SetPolicyResponse {
            version: request.version,
            ops: summary.ops.keys().cloned().collect(),
            opset: summary.opset,
            input: summary.input.describe(),
            outputs: summary.outputs.iter().map(|output| output.describe()).collect(),
            has_value: summary.has_value,
        }))
    }

    async fn start_acting(&self, request: Request<proto::StartActingRequest>) -> Result<Response<proto::ActingInfo>, Status> {
        let caller = caller(&request)?;
        let request = request.into_inner();
        let acting = radserve_core::ActingRequest {
            steps_per_second: request.steps_per_second,
            random_steps: request.random_steps,
            eval: request.eval,
            samples_per_insert: request.samples_per_insert,
            error_buffer: request.error_buffer,
            min_size: request.min_size,
            seed: request.seed,
            max_episodes: request.max_episodes,
            max_env_steps: request.max_env_steps,
        };
        let status = self.manager.start_acting(&caller, &request.session_id, acting).await.map_err(ServiceError::from)?;
        Ok(Response::new(convert::acting_to_proto(&status)))
    }

    async fn stop_acting(&self, request: Request<proto::StopActingRequest>) -> Result<Response<proto::ActingInfo>, Status> {
        let caller = caller(&request)?;
        let status = self.manager.stop_acting(&caller, &request.into_inner().session_id).await.map_err(ServiceError::from)?;
        Ok(Response::new(convert::acting_to_proto(&status)))
    }

    async fn update_priorities(
        &self,
        request: Request<proto::UpdatePrioritiesRequest>,
    ) -> Result<Response<proto::UpdatePrioritiesResponse>, Status> {
        let caller = caller(&request)?;
        let request = request.into_inner();
        let update = self
            .manager
            .update_priorities(&caller, &request.session_id, &request.keys, &request.priorities)
            .await
            .map_err(ServiceError::from)?;
        Ok(Response::new(proto::UpdatePrioritiesResponse { updated: update.updated as u64, missing: update.missing as u64 }))
    }

    type SampleBatchesStream = SampleStream;

    async fn sample_batches(
        &self,
        request: Request<proto::SampleBatchesRequest>,
    ) -> Result<Response<SampleStream>, Status> {
        let caller = caller(&request)?;
        Ok(Response::new(self.open_sample_stream(&caller, request.into_inner()).await?))
    }

    type SampleBatchesSharedStream = SharedSampleStream;

    async fn sample_batches_shared(
        &self,
        request: Request<Streaming<proto::SharedSampleRequest>>,
    ) -> Result<Response<SharedSampleStream>, Status> {
        let caller = caller(&request)?;
        Ok(Response::new(self.open_shared_sample_stream(&caller, request.into_inner()).await?))
    }
}

/// An Act stream: each request (a reset or a step) answered in order.
struct ActRequests {
    service: RadServeService,
    caller: Principal,
    inbound: Streaming<proto::ActRequest>,
}

impl Source for ActRequests {
    type Input = proto::ActRequest;
    type Message = proto::ActResponse;

    async fn next(&mut self) -> Option<Result<proto::ActRequest, Status>> {
        self.inbound.next().await
    }

    async fn make(&mut self, request: proto::ActRequest) -> Result<proto::ActResponse, Status> {
        Ok(self.service.act_once(&self.caller, request).await?)
    }
}
