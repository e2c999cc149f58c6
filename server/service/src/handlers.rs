use std::pin::Pin;
use std::sync::Arc;
use std::time::{Duration, Instant};

use radserve_core::principal::log_id;
use radserve_core::{CoreError, Principal, SessionExtras, SessionManager};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use tracing::debug;

use radserve_replay::{Batch, HeldSlots, InFlight, Output, Producer, SharedRing};

use crate::acting::{self, OpenChannels};
use crate::handoff::{HandoffSocket, PeerPolicy};
use crate::convert::{self, observation_tensor};
use crate::error::{Result as ServiceResult, ServiceError};
use crate::proto::{self, act_request, act_response, rad_serve_server::RadServe};

/// Responses of an `Act` stream that may wait for the client to read them.
const ACT_STREAM_BUFFER: usize = 2;

/// Chunk messages of a SampleBatches stream that may wait for the client to read them.
const SAMPLE_STREAM_BUFFER: usize = 4;

/// Batch descriptors of a SampleBatchesShared stream that may wait for the client to read them.
const SHARED_STREAM_BUFFER: usize = 2;

/// How long a SampleBatchesShared call may wait for its `start` message: a client that opens the
/// stream and sends nothing would otherwise hold the call (and its task) for as long as the
/// connection lives.
pub const FIRST_MESSAGE_TIMEOUT: Duration = Duration::from_secs(10);

#[derive(Clone)]
pub struct RadServeService {
    manager: Arc<SessionManager>,
    /// Threads that augment minibatches (never a tokio worker).
    augment_pool: Arc<rayon::ThreadPool>,
    /// Sessions with a shared-memory acting channel open.
    acting_channels: OpenChannels,
    /// Who may receive shared memory on this host.
    peers: PeerPolicy,
    /// Becomes true when the server starts shutting down: every open stream then ends.
    stopping: watch::Receiver<bool>,
}

/// Ends the streams of a service: `stop()` when the server begins to shut down.
pub struct StreamStopper(watch::Sender<bool>);

impl StreamStopper {
    pub fn stop(&self) {
        self.0.send_replace(true);
    }
}

/// Resolves once `stopping` turns true (never, if its sender is gone without stopping).
pub(crate) async fn stopped(mut stopping: watch::Receiver<bool>) {
    if stopping.wait_for(|stop| *stop).await.is_err() {
        std::future::pending::<()>().await;
    }
}

/// Runs `work` on a task of its own and waits for it: dropping the caller's future (tonic does when
/// the client's deadline passes or the client leaves) does not stop `work` halfway.
async fn run_to_end<T: Send + 'static>(
    work: impl std::future::Future<Output = ServiceResult<T>> + Send + 'static,
) -> ServiceResult<T> {
    tokio::spawn(work).await.unwrap_or_else(|error| Err(ServiceError::Internal(format!("the call's task failed: {error}"))))
}

/// When the client stops waiting, from its `grpc-timeout` header (gRPC over HTTP/2: an ASCII
/// integer of at most 8 digits and a unit, H M S m u n), measured from now.
/// A task that ends when this is dropped.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Who made the request: the authentication layer puts the principal in every request it lets
/// through (`crate::auth`), so a request without one never passed it.
pub(crate) fn caller<T>(request: &Request<T>) -> ServiceResult<Principal> {
    request.extensions().get::<Principal>().cloned().ok_or_else(|| {
        ServiceError::Unauthenticated("this request did not pass the server's authentication layer".into())
    })
}

pub fn client_deadline<T>(request: &Request<T>) -> Option<Instant> {
    let value = request.metadata().get("grpc-timeout")?.to_str().ok()?;
    let (digits, unit) = value.split_at(value.len().checked_sub(1)?);
    if digits.is_empty() || digits.len() > 8 {
        return None;
    }
    let amount: u64 = digits.parse().ok()?;
    let timeout = match unit {
        "H" => Duration::from_secs(amount.checked_mul(3600)?),
        "M" => Duration::from_secs(amount.checked_mul(60)?),
        "S" => Duration::from_secs(amount),
        "m" => Duration::from_millis(amount),
        "u" => Duration::from_micros(amount),
        "n" => Duration::from_nanos(amount),
        _ => return None,
    };
    Instant::now().checked_add(timeout)
}

fn check_deadline(deadline: Option<Instant>, what: &str) -> ServiceResult<()> {
    match deadline {
        Some(deadline) if Instant::now() >= deadline => Err(ServiceError::TooLate(format!(
            "the {what} waited for the session (another call on it was running) past the client's deadline; it was \
             not sent to the simulators, and the session is as it was"
        ))),
        _ => Ok(()),
    }
}

/// The next message of a bidirectional stream, or None once it ended or the server began to stop
/// (the client then gets the shutdown status).
pub(crate) async fn next_or_stop<M, T>(
    inbound: &mut Streaming<M>,
    stopping: &watch::Receiver<bool>,
    sender: &mpsc::Sender<Result<T, Status>>,
) -> Option<Result<M, Status>> {
    tokio::select! {
        message = inbound.next() => message,
        () = stopped(stopping.clone()) => {
            end_with_shutdown(sender).await;
            None
        }
    }
}

/// Ends a stream with the shutdown status; a client that does not read within a second misses it
/// (its stream then just ends: nothing it would read is lost).
pub(crate) async fn end_with_shutdown<T>(sender: &mpsc::Sender<Result<T, Status>>) {
    end_with(sender, ServiceError::StreamEnded).await;
}

/// A batch the producer made, or None when the stream is over: the producer finished, or failed
/// (the client then gets its error's status).
async fn batch_or_end<T>(batch: Option<radserve_replay::Result<Batch>>, sender: &mpsc::Sender<Result<T, Status>>) -> Option<Batch> {
    match batch? {
        Ok(batch) => Some(batch),
        Err(error) => {
            let _ = sender.send(Err(ServiceError::from(error).into())).await;
            None
        }
    }
}

/// Runs a sample stream until it ends or its session is closed, then lets go of what it holds (the
/// session's lease and the stream's memory). A stream ends with its session: it would otherwise
/// keep the session's buffer alive after the session's memory was returned to the budget.
async fn until_session_closed<T>(
    stream: impl std::future::Future<Output = ()>,
    holds: StreamHolds,
    sender: &mpsc::Sender<Result<T, Status>>,
    session_id: &str,
) {
    let (lease, _memory) = holds;
    tokio::select! {
        () = stream => {}
        () = lease.session_closed() => {
            debug!(session = log_id(session_id), "sample stream ended: its session was closed");
            end_with(sender, ServiceError::from(CoreError::UnknownSession(session_id.to_string()))).await;
        }
    }
}

/// Ends a stream with `error`'s status, unless its client does not read within a second.
async fn end_with<T>(sender: &mpsc::Sender<Result<T, Status>>, error: ServiceError) {
    let _ = tokio::time::timeout(Duration::from_secs(1), sender.send(Err(error.into()))).await;
}

/// Sends `item` unless the server stops or the client leaves first; false when it was not sent.
pub(crate) async fn send_or_stop<T>(sender: &mpsc::Sender<Result<T, Status>>, item: T, stopping: &watch::Receiver<bool>) -> bool {
    tokio::select! {
        sent = sender.send(Ok(item)) => sent.is_ok(),
        () = stopped(stopping.clone()) => {
            end_with_shutdown(sender).await;
            false
        }
    }
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
        (RadServeService { manager, augment_pool, acting_channels: OpenChannels::default(), peers, stopping }, StreamStopper(stop))
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
                infos: convert::reset_infos_to_proto(session.reset_infos()),
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
type SampleStream = Pin<Box<dyn Stream<Item = Result<proto::BatchChunk, Status>> + Send>>;
type SharedSampleStream = Pin<Box<dyn Stream<Item = Result<proto::SharedSampleResponse, Status>> + Send>>;

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
        self.manager.close_session(&caller, &request.into_inner().session_id).await.map_err(ServiceError::from)?;
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
        let caller = caller(&request)?;
        let mut inbound = request.into_inner();
        let (sender, receiver) = mpsc::channel(ACT_STREAM_BUFFER);
        let service = self.clone();
        let stopping = self.stopping.clone();
        tokio::spawn(async move {
            loop {
                let Some(message) = next_or_stop(&mut inbound, &stopping, &sender).await else { break };
                let outcome = match message {
                    Ok(request) => service.act_once(&caller, request).await.map_err(Status::from),
                    Err(status) => Err(status),
                };
                let outcome = match outcome {
                    Ok(response) => response,
                    Err(status) => {
                        let _ = sender.send(Err(status)).await;
                        break;
                    }
                };
                // Not sent: the client left or the server stops; stop reading its requests.
                if !send_or_stop(&sender, outcome, &stopping).await {
                    break;
                }
            }
            debug!("act stream ended");
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
            acting::open(self.manager.clone(), caller, &session_id, &self.acting_channels, self.peers.clone())
                .await
                .map_err(Status::from)?;
        tokio::spawn(channel.serve(session_id));
        Ok(Response::new(description))
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

/// A checked stream, ready to run: its producer, and what it holds while it runs (the session's
/// lease and the memory its batches take).
struct StreamStart {
    producer: Producer,
    action_space: radserve_core::Space,
    holds: StreamHolds,
}

/// What a running stream holds: its session's lease and the memory its batches take.
type StreamHolds = (radserve_core::LeaseHold, radserve_core::budget::Reservation);

impl RadServeService {
    /// Everything a sample stream needs is checked here, before it starts.
    async fn start_stream(&self, caller: &Principal, request: &proto::SampleBatchesRequest) -> ServiceResult<StreamStart> {
        let spec = convert::sample_spec_from_proto(request)?;
        let source = self.manager.replay_source(caller, &request.session_id).await?;
        let lease = self.manager.hold(caller, &request.session_id)?;
        let producer = Producer::new(source.buffer, source.format, spec)?.with_permit(source.permit);
        let memory = self.manager.reserve_stream(caller, producer.stream_memory_bytes(), producer.prefetch())?;
        Ok(StreamStart { producer, action_space: source.action_space, holds: (lease, memory) })
    }

    async fn open_sample_stream(&self, caller: &Principal, request: proto::SampleBatchesRequest) -> ServiceResult<SampleStream> {
        let StreamStart { producer, action_space, holds } = self.start_stream(caller, &request).await?;
        let chunk_bytes = convert::chunk_bytes(request.chunk_bytes)?;
        let (mut ready, recycler) = producer.start(self.augment_pool.clone(), Output::Heap);
        let (sender, receiver) = mpsc::channel(SAMPLE_STREAM_BUFFER);
        let session_id = request.session_id;
        let (repeat_first_batch, max_batches) = (request.repeat_first_batch, request.max_batches);
        let stopping = self.stopping.clone();
        let metrics = self.manager.metrics().clone();
        tokio::spawn(async move {
            let stream = async {
                let mut in_flight = InFlight::new(recycler);
                loop {
                    in_flight.recycle();
                    // A client that leaves while the producer waits for data must still free it.
                    let batch = tokio::select! {
                        batch = ready.recv() => batch,
                        () = sender.closed() => {
                            debug!(session = log_id(&session_id), "sample stream cancelled while waiting");
                            return;
                        }
                        () = stopped(stopping.clone()) => {
                            end_with_shutdown(&sender).await;
                            return;
                        }
                    };
                    let Some(batch) = batch_or_end(batch, &sender).await else { break };
                    let (chunks, observation_buffers) = convert::batch_to_chunks(batch, &action_space, chunk_bytes);
                    in_flight.track(observation_buffers);
                    if repeat_first_batch {
                        drop(ready);
                        // The same chunks over and over (cloning Bytes, not data): the transport alone.
                        for index in 0..max_batches.unwrap_or(u64::MAX) {
                            for chunk in &chunks {
                                let chunk = proto::BatchChunk { batch_index: index, ..chunk.clone() };
                                if !send_or_stop(&sender, chunk, &stopping).await {
                                    return;
                                }
                            }
                            metrics.record_batch();
                        }
                        return;
                    }
                    for chunk in chunks {
                        // Not sent: the client left or the server stops; dropping `ready` stops the producer.
                        if !send_or_stop(&sender, chunk, &stopping).await {
                            debug!(session = log_id(&session_id), "sample stream ended before its batch was sent");
                            return;
                        }
                    }
                    metrics.record_batch();
                }
                debug!(session = log_id(&session_id), "sample stream ended");
            };
            until_session_closed(stream, holds, &sender, &session_id).await;
        });
        Ok(Box::pin(ReceiverStream::new(receiver)))
    }

    /// The first message of a SampleBatchesShared stream: what to sample.
    async fn first_shared_request(
        inbound: &mut Streaming<proto::SharedSampleRequest>,
    ) -> ServiceResult<proto::SampleBatchesRequest> {
        use proto::shared_sample_request::Request as Inbound;
        let first = tokio::time::timeout(FIRST_MESSAGE_TIMEOUT, inbound.message()).await.map_err(|_| {
            ServiceError::TooLate(format!(
                "no SharedSampleRequest with `start` arrived within {} s of opening the stream",
                FIRST_MESSAGE_TIMEOUT.as_secs()
            ))
        })?;
        let start = match first.map_err(ServiceError::Transport)? {
            Some(proto::SharedSampleRequest { request: Some(Inbound::Start(start)) }) => start,
            _ => {
                return Err(ServiceError::BadRequest(
                    "the first SharedSampleRequest must hold `start` (the SampleBatchesRequest); releases come after it".into(),
                ))
            }
        };
        if start.repeat_first_batch {
            return Err(ServiceError::BadRequest(
                "repeat_first_batch measures the SampleBatches byte stream; it does not apply to shared memory".into(),
            ));
        }
        Ok(start)
    }

    async fn open_shared_sample_stream(
        &self,
        caller: &Principal,
        mut inbound: Streaming<proto::SharedSampleRequest>,
    ) -> ServiceResult<SharedSampleStream> {
        use proto::{shared_sample_request::Request as Inbound, shared_sample_response::Response as Outbound};
        let start = Self::first_shared_request(&mut inbound).await?;
        let StreamStart { producer, action_space, holds } = self.start_stream(caller, &start).await?;
        // A slot per batch waiting in the prefetch queue, one being filled and one the learner
        // reads: the producer never waits on a learner that releases each batch before the next.
        let slots = producer.prefetch() + 2;
        let ring = SharedRing::create(slots, producer.observation_bytes()).map_err(|error| {
            let what = format!("creating {slots} shared-memory slots of 2 x {} bytes for the batches", producer.observation_bytes());
            radserve_core::error::resource_error(&what, &error)
        })?;
        let socket = HandoffSocket::bind()
            .map_err(|error| ServiceError::Internal(format!("binding the batch memory's socket: {error}")))?;
        let region = proto::SharedMemoryRegion {
            size: ring.size_bytes() as u64,
            token: ring.token().to_vec(),
            slots: ring.slots() as u32,
            slot_bytes: ring.slot_bytes() as u64,
            socket: socket.name().to_string(),
        };
        // The learner collects the memory's descriptor while the stream runs; ending the stream
        // ends the offer (and with it the last reference to the ring outside the producer).
        let offer = {
            let (ring, peers) = (ring.clone(), self.peers.clone());
            AbortOnDrop(tokio::spawn(async move {
                drop(socket.hand_over(ring.token(), ring.fd(), &peers).await);
            }))
        };
        let (mut ready, _recycler) = producer.start(self.augment_pool.clone(), Output::Shared(ring));
        let (sender, receiver) = mpsc::channel(SHARED_STREAM_BUFFER);
        sender
            .send(Ok(proto::SharedSampleResponse { response: Some(Outbound::Region(region)) }))
            .await
            .expect("the receiver is still here");
        let session_id = start.session_id;
        let stopping = self.stopping.clone();
        let metrics = self.manager.metrics().clone();
        tokio::spawn(async move {
            let _offer = offer;
            let stream = async {
                // Slots of batches sent and not yet released; releasing one hands it back to the producer.
                let mut held = HeldSlots::default();
                loop {
                    tokio::select! {
                        batch = ready.recv() => {
                            let Some(batch) = batch_or_end(batch, &sender).await else { break };
                            let index = batch.index;
                            let (message, slot) = convert::shared_batch_to_proto(batch, &action_space);
                            held.hold(index, slot);
                            let response = proto::SharedSampleResponse { response: Some(Outbound::Batch(message)) };
                            if !send_or_stop(&sender, response, &stopping).await {
                                debug!(session = log_id(&session_id), "shared sample stream cancelled");
                                return;
                            }
                            metrics.record_batch();
                        }
                        message = inbound.message() => {
                            let released = match message {
                                Ok(Some(proto::SharedSampleRequest { request: Some(Inbound::Release(index)) })) => {
                                    held.release(index).map_err(ServiceError::from)
                                }
                                Ok(Some(_)) => Err(ServiceError::BadRequest(
                                    "after the first SharedSampleRequest, requests may only release batches".into(),
                                )),
                                // The client closed its side or left: dropping `ready` stops the producer.
                                Ok(None) | Err(_) => {
                                    debug!(session = log_id(&session_id), "shared sample stream closed by the client");
                                    return;
                                }
                            };
                            if let Err(error) = released {
                                let _ = sender.send(Err(error.into())).await;
                                return;
                            }
                        }
                        () = sender.closed() => {
                            debug!(session = log_id(&session_id), "shared sample stream cancelled");
                            return;
                        }
                        () = stopped(stopping.clone()) => {
                            end_with_shutdown(&sender).await;
                            return;
                        }
                    }
                }
                debug!(session = log_id(&session_id), "shared sample stream ended");
            };
            until_session_closed(stream, holds, &sender, &session_id).await;
        });
        Ok(Box::pin(ReceiverStream::new(receiver)))
    }
}
