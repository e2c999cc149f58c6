//! The sample streams: SampleBatches (each batch as chunks of bytes in gRPC messages) and
//! SampleBatchesShared (each batch written into shared memory the learner maps once, released by
//! the learner when read). Both are run by `streams::pump` until they end, their client leaves,
//! the server stops or their session is closed.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use radserve_core::metrics::CoreMetrics;
use radserve_core::principal::log_id;
use radserve_core::{CoreError, LeaseHold, Principal, Progress, Space};
use radserve_replay::{Batch, HeldSlots, InFlight, Output, Producer, SharedRing};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Status, Streaming};
use tracing::debug;

use crate::convert;
use crate::error::{Result as ServiceResult, ServiceError};
use crate::handlers::{RadServeService, SampleStream, SharedSampleStream};
use crate::handoff::HandoffSocket;
use crate::proto::{self, shared_sample_request::Request as Inbound, shared_sample_response::Response as Outbound};
use crate::streams::{end_with, pump, AbortOnDrop, Source};

/// Chunk messages of a SampleBatches stream that may wait for the client to read them.
const SAMPLE_STREAM_BUFFER: usize = 4;

/// Batch descriptors of a SampleBatchesShared stream that may wait for the client to read them.
const SHARED_STREAM_BUFFER: usize = 2;

/// How long a SampleBatchesShared call may wait for its `start` message: a client that opens the
/// stream and sends nothing would otherwise hold the call (and its task) for as long as the
/// connection lives.
pub const FIRST_MESSAGE_TIMEOUT: Duration = Duration::from_secs(10);

/// The batches a producer makes, as it hands them over (None: it finished).
type Ready = mpsc::Receiver<radserve_replay::Result<Batch>>;

/// A checked stream, ready to run: its producer, and what it holds while it runs (the session's
/// lease and the memory its batches take).
struct StreamStart {
    producer: Producer,
    action_space: Space,
    holds: StreamHolds,
}

/// What a running stream holds: its session's lease and the memory its batches take.
type StreamHolds = (LeaseHold, radserve_core::budget::Reservation);

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

    pub(crate) async fn open_sample_stream(
        &self,
        caller: &Principal,
        request: proto::SampleBatchesRequest,
    ) -> ServiceResult<SampleStream> {
        let StreamStart { producer, action_space, holds } = self.start_stream(caller, &request).await?;
        let chunk_bytes = convert::chunk_bytes(request.chunk_bytes)?;
        let (ready, recycler) = producer.start(self.augment_pool.clone(), Output::Heap);
        let source = Chunks {
            ready,
            in_flight: InFlight::new(recycler),
            pending: VecDeque::new(),
            action_space,
            chunk_bytes,
            metrics: self.manager.metrics().clone(),
            progress: holds.0.progress(),
        };
        let (sender, receiver) = mpsc::channel(SAMPLE_STREAM_BUFFER);
        tokio::spawn(run(source, holds, sender, self.stopping.clone(), request.session_id, "sample stream"));
        Ok(Box::pin(ReceiverStream::new(receiver)))
    }

    pub(crate) async fn open_shared_sample_stream(
        &self,
        caller: &Principal,
        mut inbound: Streaming<proto::SharedSampleRequest>,
    ) -> ServiceResult<SharedSampleStream> {
        let start = first_shared_request(&mut inbound).await?;
        let StreamStart { producer, action_space, holds } = self.start_stream(caller, &start).await?;
        let (ring, region, offer) = self.offer_ring(&producer)?;
        let (ready, _recycler) = producer.start(self.augment_pool.clone(), Output::Shared(ring));
        let (sender, receiver) = mpsc::channel(SHARED_STREAM_BUFFER);
        let region = proto::SharedSampleResponse { response: Some(Outbound::Region(region)) };
        sender.send(Ok(region)).await.expect("the receiver is still here");
        let source = SharedBatches {
            ready,
            inbound,
            held: HeldSlots::default(),
            action_space,
            metrics: self.manager.metrics().clone(),
            progress: holds.0.progress(),
            _offer: offer,
            finished: false,
        };
        tokio::spawn(run(source, holds, sender, self.stopping.clone(), start.session_id, "shared sample stream"));
        Ok(Box::pin(ReceiverStream::new(receiver)))
    }

    /// The shared memory a stream's batches are written into, what the learner is told of it, and
    /// the task that hands its descriptor to the learner (the offer ends with the stream, and with
    /// it the last reference to the ring outside the producer).
    fn offer_ring(&self, producer: &Producer) -> ServiceResult<(Arc<SharedRing>, proto::SharedMemoryRegion, AbortOnDrop)> {
        // A slot per batch waiting in the prefetch queue, one being filled and one the learner
        // reads: the producer never waits on a learner that releases each batch before the next.
        let slots = producer.prefetch() + 2;
        let regions = producer.region_bytes();
        let ring = SharedRing::create(slots, &regions).map_err(|error| {
            let what = format!("creating {slots} shared-memory slots of {regions:?} bytes for the batches");
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
        let (offered, peers) = (ring.clone(), self.peers.clone());
        let offer = AbortOnDrop(tokio::spawn(async move {
            drop(socket.hand_over(offered.token(), offered.fd(), &peers).await);
        }));
        Ok((ring, region, offer))
    }
}

/// Runs a sample stream until it ends or its session is closed, then lets go of what it holds (the
/// session's lease and the stream's memory). A stream ends with its session: it would otherwise
/// keep the session's buffer alive after the session's memory was returned to the budget.
async fn run<S: Source>(
    source: S,
    holds: StreamHolds,
    sender: mpsc::Sender<Result<S::Message, Status>>,
    stopping: watch::Receiver<bool>,
    session_id: String,
    what: &'static str,
) {
    let (lease, _memory) = holds;
    tokio::select! {
        ended = pump(source, &sender, &stopping) => {
            debug!(session = log_id(&session_id), ?ended, "{what} ended");
        }
        () = lease.session_closed() => {
            debug!(session = log_id(&session_id), "{what} ended: its session was closed");
            end_with(&sender, ServiceError::from(CoreError::UnknownSession(session_id.clone()))).await;
        }
    }
}

/// The first message of a SampleBatchesShared stream: what to sample.
async fn first_shared_request(inbound: &mut Streaming<proto::SharedSampleRequest>) -> ServiceResult<proto::SampleBatchesRequest> {
    let first = tokio::time::timeout(FIRST_MESSAGE_TIMEOUT, inbound.message()).await.map_err(|_| {
        ServiceError::TooLate(format!(
            "no SharedSampleRequest with `start` arrived within {} s of opening the stream",
            FIRST_MESSAGE_TIMEOUT.as_secs()
        ))
    })?;
    match first.map_err(ServiceError::Transport)? {
        Some(proto::SharedSampleRequest { request: Some(Inbound::Start(start)) }) => Ok(start),
        _ => Err(ServiceError::BadRequest(
            "the first SharedSampleRequest must hold `start` (the SampleBatchesRequest); releases come after it".into(),
        )),
    }
}

/// A batch the producer made, or None when it finished; its failure ends the stream with its status.
fn batch_or_end(batch: Option<radserve_replay::Result<Batch>>) -> Option<Result<Batch, Status>> {
    batch.map(|batch| batch.map_err(|error| ServiceError::from(error).into()))
}

/// SampleBatches: each batch as chunks of at most `chunk_bytes` of its fields.
struct Chunks {
    ready: Ready,
    /// The observation buffers of chunks sent, given back to the producer once the client has them.
    in_flight: InFlight,
    /// The chunks of the current batch not sent yet.
    pending: VecDeque<proto::BatchChunk>,
    action_space: Space,
    chunk_bytes: usize,
    metrics: Arc<CoreMetrics>,
    /// Marked at every batch the client takes: an unread stream stops holding its session.
    progress: Progress,
}

impl Source for Chunks {
    type Input = proto::BatchChunk;
    type Message = proto::BatchChunk;

    async fn next(&mut self) -> Option<Result<proto::BatchChunk, Status>> {
        if self.pending.is_empty() {
            self.in_flight.recycle();
            let batch = match batch_or_end(self.ready.recv().await)? {
                Ok(batch) => batch,
                Err(status) => return Some(Err(status)),
            };
            let (chunks, observation_buffers) = convert::batch_to_chunks(batch, &self.action_space, self.chunk_bytes);
            self.in_flight.track(observation_buffers);
            self.pending.extend(chunks);
        }
        self.pending.pop_front().map(Ok)
    }

    async fn make(&mut self, chunk: proto::BatchChunk) -> Result<proto::BatchChunk, Status> {
        Ok(chunk)
    }

    fn sent(&mut self) {
        self.progress.mark();
        if self.pending.is_empty() {
            self.metrics.record_batch();
        }
    }
}

/// SampleBatchesShared: each batch's descriptor (its slot in the shared memory and its small
/// fields); the client's requests release the slots it has read.
struct SharedBatches {
    ready: Ready,
    inbound: Streaming<proto::SharedSampleRequest>,
    /// Slots of batches sent and not yet released; releasing one hands it back to the producer.
    held: HeldSlots,
    action_space: Space,
    metrics: Arc<CoreMetrics>,
    /// Marked at every batch the client takes: an unread stream stops holding its session.
    progress: Progress,
    /// The hand-off of the memory's descriptor, for as long as the stream runs.
    _offer: AbortOnDrop,
    /// The producer made its last batch (max_batches, or a rollout's last epoch): the stream ends
    /// once the client has released every batch it holds, so that a client that maps the memory
    /// after the last batch was sent still finds the hand-off socket open.
    finished: bool,
}

impl Source for SharedBatches {
    type Input = proto::SharedSampleResponse;
    type Message = proto::SharedSampleResponse;

    async fn next(&mut self) -> Option<Result<proto::SharedSampleResponse, Status>> {
        loop {
            if self.finished && self.held.is_empty() {
                return None;
            }
            tokio::select! {
                batch = self.ready.recv(), if !self.finished => {
                    let Some(batch) = batch_or_end(batch) else {
                        self.finished = true;
                        continue;
                    };
                    let batch = match batch {
                        Ok(batch) => batch,
                        Err(status) => return Some(Err(status)),
                    };
                    let index = batch.index;
                    let (message, slot) = convert::shared_batch_to_proto(batch, &self.action_space);
                    self.held.hold(index, slot);
                    return Some(Ok(proto::SharedSampleResponse { response: Some(Outbound::Batch(message)) }));
                }
                message = self.inbound.message() => match message {
                    Ok(Some(proto::SharedSampleRequest { request: Some(Inbound::Release(index)) })) => {
                        if let Err(error) = self.held.release(index) {
                            return Some(Err(ServiceError::from(error).into()));
                        }
                    }
                    Ok(Some(_)) => {
                        return Some(Err(ServiceError::BadRequest(
                            "after the first SharedSampleRequest, requests may only release batches".into(),
                        )
                        .into()))
                    }
                    // The client closed its side or left: dropping `ready` stops the producer.
                    Ok(None) | Err(_) => return None,
                },
            }
        }
    }

    async fn make(&mut self, message: proto::SharedSampleResponse) -> Result<proto::SharedSampleResponse, Status> {
        Ok(message)
    }

    fn sent(&mut self) {
        self.progress.mark();
        self.metrics.record_batch();
    }
}
