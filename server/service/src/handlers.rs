use std::pin::Pin;
use std::sync::Arc;
use std::time::{Duration, Instant};

use radserve_core::{SessionExtras, SessionManager};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use tracing::debug;

use crate::acting::{self, OpenChannels};
use crate::convert::{self, observation_tensor};
use radserve_replay::{Output, Producer, SharedRing, Slot};

use crate::error::{replay_status, to_status};
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

/// The status an open stream ends with when the server shuts down.
fn shutting_down() -> Status {
    Status::unavailable("the server is shutting down; this stream ended (its session is closed at exit)")
}

/// Resolves once `stopping` turns true (never, if its sender is gone without stopping).
async fn stopped(mut stopping: watch::Receiver<bool>) {
    if stopping.wait_for(|stop| *stop).await.is_err() {
        std::future::pending::<()>().await;
    }
}

/// Runs `work` on a task of its own and waits for it: dropping the caller's future (tonic does when
/// the client's deadline passes or the client leaves) does not stop `work` halfway.
async fn run_to_end<T: Send + 'static>(
    work: impl std::future::Future<Output = Result<T, Status>> + Send + 'static,
) -> Result<T, Status> {
    tokio::spawn(work).await.unwrap_or_else(|error| Err(Status::internal(format!("the call's task failed: {error}"))))
}

/// When the client stops waiting, from its `grpc-timeout` header (gRPC over HTTP/2: an ASCII
/// integer of at most 8 digits and a unit, H M S m u n), measured from now.
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

fn check_deadline(deadline: Option<Instant>, what: &str) -> Result<(), Status> {
    match deadline {
        Some(deadline) if Instant::now() >= deadline => Err(Status::deadline_exceeded(format!(
            "the {what} waited for the session (another call on it was running) past the client's deadline; it was \
             not sent to the simulators, and the session is as it was"
        ))),
        _ => Ok(()),
    }
}

/// Ends a stream with the shutdown status; a client that does not read within a second misses it
/// (its stream then just ends: nothing it would read is lost).
async fn end_with_shutdown<T>(sender: &mpsc::Sender<Result<T, Status>>) {
    let _ = tokio::time::timeout(Duration::from_secs(1), sender.send(Err(shutting_down()))).await;
}

/// Sends `item` unless the server stops or the client leaves first; false when it was not sent.
async fn send_or_stop<T>(sender: &mpsc::Sender<Result<T, Status>>, item: T, stopping: &watch::Receiver<bool>) -> bool {
    tokio::select! {
        sent = sender.send(Ok(item)) => sent.is_ok(),
        () = stopped(stopping.clone()) => {
            end_with_shutdown(sender).await;
            false
        }
    }
}

impl RadServeService {
    pub fn new(manager: Arc<SessionManager>, augment_pool: Arc<rayon::ThreadPool>) -> (RadServeService, StreamStopper) {
        let (stop, stopping) = watch::channel(false);
        (RadServeService { manager, augment_pool, acting_channels: OpenChannels::default(), stopping }, StreamStopper(stop))
    }

    /// Resets and steps run to their end in a task of their own, even when the caller stops waiting
    /// (its deadline passed, it left): cut short after the workers got it, a step would leave the envs
    /// a step ahead of the session's stacks and replay. What the deadline can still prevent is
    /// checked once the session is free: a request whose client deadline has passed by then is
    /// answered DEADLINE_EXCEEDED without being sent.
    async fn reset(&self, request: proto::ResetRequest, deadline: Option<Instant>) -> Result<proto::ResetResponse, Status> {
        let session = self.manager.get(&request.session_id).map_err(to_status)?;
        run_to_end(async move {
            let mut session = session.lock().await;
            check_deadline(deadline, "Reset")?;
            let obs = session.reset(request.seed).await.map_err(to_status)?;
            Ok(proto::ResetResponse { obs: Some(observation_tensor(&session.observation_space, session.num_envs(), obs)) })
        })
        .await
    }

    async fn step(&self, request: proto::StepRequest, deadline: Option<Instant>) -> Result<proto::StepResponse, Status> {
        let (dtype, shape) = convert::tensor_header(request.actions.as_ref(), "actions")?;
        let actions = request.actions.map(|tensor| tensor.data).unwrap_or_default();
        let session = self.manager.get(&request.session_id).map_err(to_status)?;
        run_to_end(async move {
            let mut session = session.lock().await;
            check_deadline(deadline, "Step")?;
            let outcome = session.step(dtype, &shape, &actions).await.map_err(to_status)?;
            Ok(convert::step_to_proto(&session.observation_space, outcome))
        })
        .await
    }

    /// A stream's batches produced ahead must fit the server's per-stream limit and its memory
    /// budget; the reservation is held for as long as the stream runs.
    fn reserve_stream_memory(&self, producer: &Producer) -> Result<radserve_core::budget::Reservation, Status> {
        self.check_stream_memory(producer)?;
        let what = format!("a sample stream of (prefetch {} + 2) batches", producer.prefetch());
        self.manager.reserve_memory(producer.stream_memory_bytes(), &what).map_err(to_status)
    }

    /// A stream's batches produced ahead must fit the server's per-stream limit.
    fn check_stream_memory(&self, producer: &Producer) -> Result<(), Status> {
        let limit = self.manager.limits().stream_memory_bytes;
        let needed = producer.stream_memory_bytes();
        if needed > limit {
            return Err(Status::resource_exhausted(format!(
                "this stream would hold {needed} bytes of batches ((prefetch {} + 2) batches of observations), over \
                 this server's limit of {limit} (limits.stream_memory_bytes): lower prefetch or batch_size",
                producer.prefetch()
            )));
        }
        Ok(())
    }

    async fn act_once(&self, request: proto::ActRequest) -> Result<proto::ActResponse, Status> {
        let response = match request.request {
            Some(act_request::Request::Reset(reset)) => act_response::Response::Reset(self.reset(reset, None).await?),
            Some(act_request::Request::Step(step)) => act_response::Response::Step(self.step(step, None).await?),
            None => return Err(Status::invalid_argument("ActRequest must hold a reset or a step")),
        };
        Ok(proto::ActResponse { response: Some(response) })
    }
}

type ActStream = Pin<Box<dyn Stream<Item = Result<proto::ActResponse, Status>> + Send>>;
type SampleStream = Pin<Box<dyn Stream<Item = Result<proto::BatchChunk, Status>> + Send>>;
type SharedSampleStream = Pin<Box<dyn Stream<Item = Result<proto::SharedSampleResponse, Status>> + Send>>;

#[tonic::async_trait]
impl RadServe for RadServeService {
    async fn list_envs(&self, request: Request<proto::ListEnvsRequest>) -> Result<Response<proto::ListEnvsResponse>, Status> {
        let prefix = request.into_inner().prefix;
        radserve_core::bounds::check_len("prefix", &prefix, radserve_core::bounds::MAX_ID_BYTES).map_err(to_status)?;
        let catalog = self.manager.catalog().await.map_err(to_status)?;
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
        let request = request.into_inner();
        let options = convert::options_from_proto(&request.options)?;
        let info = self
            .manager
            .create_session(
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
            .map_err(to_status)?;
        Ok(Response::new(convert::session_info_to_proto(&info)))
    }

    async fn list_sessions(
        &self,
        _request: Request<proto::ListSessionsRequest>,
    ) -> Result<Response<proto::ListSessionsResponse>, Status> {
        let sessions = self.manager.list_sessions().iter().map(convert::session_summary_to_proto).collect();
        let idle_timeout_seconds = self.manager.idle_timeout().map_or(0.0, |timeout| timeout.as_secs_f64());
        Ok(Response::new(proto::ListSessionsResponse { sessions, idle_timeout_seconds }))
    }

    async fn describe_session(
        &self,
        request: Request<proto::DescribeSessionRequest>,
    ) -> Result<Response<proto::SessionInfo>, Status> {
        let info = self.manager.describe(&request.into_inner().session_id).await.map_err(to_status)?;
        Ok(Response::new(convert::session_info_to_proto(&info)))
    }

    async fn close_session(
        &self,
        request: Request<proto::CloseSessionRequest>,
    ) -> Result<Response<proto::CloseSessionResponse>, Status> {
        self.manager.close_session(&request.into_inner().session_id).await.map_err(to_status)?;
        Ok(Response::new(proto::CloseSessionResponse {}))
    }

    async fn reset(&self, request: Request<proto::ResetRequest>) -> Result<Response<proto::ResetResponse>, Status> {
        let deadline = client_deadline(&request);
        Ok(Response::new(RadServeService::reset(self, request.into_inner(), deadline).await?))
    }

    async fn step(&self, request: Request<proto::StepRequest>) -> Result<Response<proto::StepResponse>, Status> {
        let deadline = client_deadline(&request);
        Ok(Response::new(RadServeService::step(self, request.into_inner(), deadline).await?))
    }

    type ActStream = ActStream;

    async fn act(&self, request: Request<Streaming<proto::ActRequest>>) -> Result<Response<ActStream>, Status> {
        let mut inbound = request.into_inner();
        let (sender, receiver) = mpsc::channel(ACT_STREAM_BUFFER);
        let service = self.clone();
        let stopping = self.stopping.clone();
        tokio::spawn(async move {
            loop {
                let message = tokio::select! {
                    message = inbound.next() => message,
                    () = stopped(stopping.clone()) => {
                        end_with_shutdown(&sender).await;
                        break;
                    }
                };
                let Some(message) = message else { break };
                let outcome = match message {
                    Ok(request) => service.act_once(request).await,
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
        let session_id = request.into_inner().session_id;
        let (description, channel) = acting::open(self.manager.clone(), &session_id, &self.acting_channels).await?;
        tokio::spawn(channel.serve(session_id));
        Ok(Response::new(description))
    }

    type SampleBatchesStream = SampleStream;

    async fn sample_batches(
        &self,
        request: Request<proto::SampleBatchesRequest>,
    ) -> Result<Response<SampleStream>, Status> {
        let request = request.into_inner();
        let spec = convert::sample_spec_from_proto(&request)?;
        let source = self.manager.replay_source(&request.session_id).await.map_err(to_status)?;
        let lease = self.manager.hold(&request.session_id).map_err(to_status)?;
        // Everything is checked here, before the stream starts.
        let producer = Producer::new(source.buffer, source.format, spec).map_err(replay_status)?.with_permit(source.permit);
        let memory = self.reserve_stream_memory(&producer)?;
        let chunk_bytes = convert::chunk_bytes(request.chunk_bytes)?;
        let (mut ready, recycler) = producer.start(self.augment_pool.clone(), Output::Heap);
        let (sender, receiver) = mpsc::channel(SAMPLE_STREAM_BUFFER);
        let session_id = request.session_id;
        let (repeat_first_batch, max_batches) = (request.repeat_first_batch, request.max_batches);
        let stopping = self.stopping.clone();
        tokio::spawn(async move {
            // The open stream keeps the session's lease alive and its memory reserved.
            let (_lease, _memory) = (lease, memory);
            // Observation buffers of sent batches, handed back to the producer once tonic has
            // dropped every chunk that points into them.
            let mut in_flight: Vec<Arc<Vec<u8>>> = Vec::new();
            loop {
                let (done, pending): (Vec<_>, Vec<_>) =
                    in_flight.drain(..).partition(|buffer| Arc::strong_count(buffer) == 1);
                in_flight = pending;
                for buffer in done {
                    if let Ok(buffer) = Arc::try_unwrap(buffer) {
                        let _ = recycler.send(buffer);
                    }
                }
                // A client that leaves while the producer waits for data must still free it.
                let batch = tokio::select! {
                    batch = ready.recv() => batch,
                    () = sender.closed() => {
                        debug!(session = %session_id, "sample stream cancelled while waiting");
                        return;
                    }
                    () = stopped(stopping.clone()) => {
                        end_with_shutdown(&sender).await;
                        return;
                    }
                };
                let Some(batch) = batch else { break };
                let batch = match batch {
                    Ok(batch) => batch,
                    Err(error) => {
                        let _ = sender.send(Err(replay_status(error))).await;
                        break;
                    }
                };
                let (chunks, observation_buffers) = convert::batch_to_chunks(batch, &source.action_space, chunk_bytes);
                in_flight.extend(observation_buffers);
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
                    }
                    return;
                }
                for chunk in chunks {
                    // Not sent: the client left or the server stops; dropping `ready` stops the producer.
                    if !send_or_stop(&sender, chunk, &stopping).await {
                        debug!(session = %session_id, "sample stream ended before its batch was sent");
                        return;
                    }
                }
            }
            debug!(session = %session_id, "sample stream ended");
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(receiver))))
    }

    type SampleBatchesSharedStream = SharedSampleStream;

    async fn sample_batches_shared(
        &self,
        request: Request<Streaming<proto::SharedSampleRequest>>,
    ) -> Result<Response<SharedSampleStream>, Status> {
        use proto::{shared_sample_request::Request as Inbound, shared_sample_response::Response as Outbound};
        let mut inbound = request.into_inner();
        let first = tokio::time::timeout(FIRST_MESSAGE_TIMEOUT, inbound.message()).await.map_err(|_| {
            Status::deadline_exceeded(format!(
                "no SharedSampleRequest with `start` arrived within {} s of opening the stream",
                FIRST_MESSAGE_TIMEOUT.as_secs()
            ))
        })?;
        let start = match first? {
            Some(proto::SharedSampleRequest { request: Some(Inbound::Start(start)) }) => start,
            _ => {
                return Err(Status::invalid_argument(
                    "the first SharedSampleRequest must hold `start` (the SampleBatchesRequest); releases come after it",
                ))
            }
        };
        if start.repeat_first_batch {
            return Err(Status::invalid_argument(
                "repeat_first_batch measures the SampleBatches byte stream; it does not apply to shared memory",
            ));
        }
        let spec = convert::sample_spec_from_proto(&start)?;
        let source = self.manager.replay_source(&start.session_id).await.map_err(to_status)?;
        let lease = self.manager.hold(&start.session_id).map_err(to_status)?;
        let producer = Producer::new(source.buffer, source.format, spec).map_err(replay_status)?.with_permit(source.permit);
        let memory = self.reserve_stream_memory(&producer)?;
        // A slot per batch waiting in the prefetch queue, one being filled and one the learner
        // reads: the producer never waits on a learner that releases each batch before the next.
        let slots = producer.prefetch() + 2;
        let ring = SharedRing::create(slots, producer.observation_bytes()).map_err(|error| {
            Status::resource_exhausted(format!(
                "could not create {slots} shared-memory slots of 2 x {} bytes for the batches: {error}",
                producer.observation_bytes()
            ))
        })?;
        let region = proto::SharedMemoryRegion {
            path: ring.path(),
            size: ring.size_bytes() as u64,
            token: ring.token().to_vec(),
            slots: ring.slots() as u32,
            slot_bytes: ring.slot_bytes() as u64,
        };
        let (mut ready, _recycler) = producer.start(self.augment_pool.clone(), Output::Shared(ring));
        let (sender, receiver) = mpsc::channel(SHARED_STREAM_BUFFER);
        sender
            .send(Ok(proto::SharedSampleResponse { response: Some(Outbound::Region(region)) }))
            .await
            .expect("the receiver is still here");
        let session_id = start.session_id;
        let stopping = self.stopping.clone();
        tokio::spawn(async move {
            let (_lease, _memory) = (lease, memory);
            // Slots of batches sent and not yet released; dropping one hands it back to the producer.
            let mut held: std::collections::HashMap<u64, Slot> = std::collections::HashMap::new();
            loop {
                tokio::select! {
                    batch = ready.recv() => {
                        let batch = match batch {
                            None => break,
                            Some(Ok(batch)) => batch,
                            Some(Err(error)) => {
                                let _ = sender.send(Err(replay_status(error))).await;
                                break;
                            }
                        };
                        let index = batch.index;
                        let (message, slot) = convert::shared_batch_to_proto(batch, &source.action_space);
                        held.insert(index, slot);
                        let response = proto::SharedSampleResponse { response: Some(Outbound::Batch(message)) };
                        if !send_or_stop(&sender, response, &stopping).await {
                            debug!(session = %session_id, "shared sample stream cancelled");
                            return;
                        }
                    }
                    message = inbound.message() => match message {
                        Ok(Some(proto::SharedSampleRequest { request: Some(Inbound::Release(index)) })) => {
                            if held.remove(&index).is_none() {
                                let mut holding: Vec<_> = held.keys().copied().collect();
                                holding.sort_unstable();
                                let _ = sender
                                    .send(Err(Status::invalid_argument(format!(
                                        "release of batch {index}, which the client does not hold (it holds {holding:?})"
                                    ))))
                                    .await;
                                return;
                            }
                        }
                        Ok(Some(_)) => {
                            let _ = sender
                                .send(Err(Status::invalid_argument(
                                    "after the first SharedSampleRequest, requests may only release batches",
                                )))
                                .await;
                            return;
                        }
                        // The client closed its side or left: dropping `ready` stops the producer.
                        Ok(None) | Err(_) => {
                            debug!(session = %session_id, "shared sample stream closed by the client");
                            return;
                        }
                    },
                    () = sender.closed() => {
                        debug!(session = %session_id, "shared sample stream cancelled");
                        return;
                    }
                    () = stopped(stopping.clone()) => {
                        end_with_shutdown(&sender).await;
                        return;
                    }
                }
            }
            debug!(session = %session_id, "shared sample stream ended");
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(receiver))))
    }
}
