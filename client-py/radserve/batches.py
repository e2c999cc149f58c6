"""Augmented minibatches from a session's replay buffer or rollout, two ways.

Over gRPC (`BatchStream`): generated protobuf classes copy a `bytes` field on every access; a 32 MB
observation would be copied twice before numpy saw it. The stream is therefore read as raw message
bytes, and each BatchChunk is parsed here with a few lines of protobuf wire format: the tensor bytes
are copied once, straight into the batch's numpy arrays.

Through shared memory (`SharedBatchStream`), for a learner on the server's host: the server writes
each batch's observations into a slot of memory this process maps, and gRPC carries only where they
are. The arrays are views of that memory, valid until the next batch is taken from the stream.
"""

from __future__ import annotations

import mmap
import queue
from dataclasses import dataclass, field
from typing import Any, Iterator, Mapping

import grpc
import numpy as np

from ._convert import NUMPY_DTYPES
from ._proto import radserve_pb2 as pb
from ._shm import receive_server_memory
from ._transport import check_delivery
from .errors import InvalidArgumentError, SharedMemoryError, from_rpc_error

# Every field of a batch but its observations; any other field is a view (obs and next_obs when the
# request names no views).
METADATA_FIELDS = ("action", "reward", "discount", "terminated", "truncated", "env_index", "step_index", "t",
                   "policy_version", "log_prob", "value", "key", "probability", "table_size", "weight", "is_first",
                   "is_last", "is_terminal", "mask")

# The uint8 fields a Batch carries as bools.
_FLAGS = ("terminated", "truncated", "is_first", "is_last", "is_terminal", "mask")

SHARING = {
    "reference": pb.DRAW_SHARING_REFERENCE,
    "shared": pb.DRAW_SHARING_SHARED,
    "independent": pb.DRAW_SHARING_INDEPENDENT,
}


@dataclass(frozen=True)
class View:
    """One named output of a batch (`sample_batches(views={"obs_aug": View("shift(4)")})`): each
    sample's `of` ("obs" or "next_obs"; default: "next_obs" for a name starting with `next_`, else
    "obs") through `augment` (a pipeline in text form; "none": the stack as stored). Views with the
    same `draws` label share their random draws stage by stage; the others draw independently."""

    augment: str = "none"
    of: "str | None" = None
    draws: "str | None" = None


_VIEW_OF = {None: pb.VIEW_OF_UNSPECIFIED, "obs": pb.VIEW_OF_OBS, "next_obs": pb.VIEW_OF_NEXT_OBS}


@dataclass(frozen=True)
class Sequence:
    """Sequences of consecutive steps of one env instead of single transitions
    (`sample_batches(sequence=radserve.Sequence(120, burn_in=40, period=40))`, R2D2's): every
    array of a batch is `[batch, length, ...]`. `length` counts the `burn_in` steps (the leading
    steps a recurrent learner only unrolls its state over); windows start every `period` steps.
    `boundary="within_episode"` (the default) starts windows in an episode and pads the steps after
    its last frame (`Batch.mask` False, zeros elsewhere: R2D2, SPR's futures);
    `"across_episodes"` runs on through episode ends, flagged by `is_first` and `is_last`
    (Dreamer). See docs/replay.md, "Sequences"."""

    length: int
    burn_in: int = 0
    period: int = 1
    boundary: str = "within_episode"


_BOUNDARIES = {"within_episode": pb.SEQUENCE_BOUNDARY_WITHIN_EPISODE,
               "across_episodes": pb.SEQUENCE_BOUNDARY_ACROSS_EPISODES}


def _sequence_request(sequence: "int | Sequence | None") -> "pb.SequenceRequest | None":
    if sequence is None:
        return None
    if isinstance(sequence, int) and not isinstance(sequence, bool):
        sequence = Sequence(sequence)
    if not isinstance(sequence, Sequence) or sequence.boundary not in _BOUNDARIES:
        raise InvalidArgumentError(
            f"sequence must be a length or a radserve.Sequence with boundary one of {sorted(_BOUNDARIES)}, got {sequence!r}")
    return pb.SequenceRequest(length=sequence.length, burn_in=sequence.burn_in, period=sequence.period,
                              boundary=_BOUNDARIES[sequence.boundary])


@dataclass
class Batch:
    """One minibatch of transitions; every array has the batch as its first dimension.

    `obs` and `next_obs` are augmented (uint8 frame stacks, or float32 states); `terminated` and
    `truncated` are bools (bootstrap through truncations: `not_done = ~terminated`); `env_index` and
    `step_index` say which environment and which Step call of the session produced each transition.
    Rollout batches carry `t`, each transition's step within the rollout (0 the oldest), and no
    `next_obs` unless asked for. `policy_version` is the version of the server-side policy that
    acted (`Client.set_policy`; -1 where none did), so a learner can see how stale a batch is;
    rollouts acted on the server also carry the head's `log_prob` of each action and the model's
    `value` (PPO's old log-probabilities and values).

    `views` holds every observation array by name: obs and next_obs, or the views the request named
    (`obs` and `next_obs` are then the views of those names, if any). With `n_step` (or `discount`),
    `reward` is the n-step return, `discount` the bootstrap's factor (0 where the episode terminated
    within the window) and `next_obs` the observation after the window: the target is
    `reward + discount * Q(next_obs)`.

    A prioritized stream's batches (`sampler="prioritized"`) carry each transition's `key` (what
    `update_priorities` names it by), the `probability` of its draw, `table_size` (the transitions
    that could be drawn) and its importance `weight`, `(table_size * probability) ** -beta` over
    the batch's largest, with the request's `importance_sampling_exponent` as beta
    (`radserve.importance_weights` computes them for another beta).

    A sequence stream's batches (`sequence=radserve.Sequence(...)`) have `[batch, length]` as the
    first two dimensions of every array: step i's observation, then the `action`, `reward`,
    `terminated` and `truncated` of the step taken from it (zero where none was); `is_first` (the
    observation is its episode's first), `is_last` (its episode's last), `is_terminal` (the last of
    an episode that terminated) and `mask` (False for padding after an episode's end).
    """

    index: int
    obs: "np.ndarray | None"
    action: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    env_index: np.ndarray
    step_index: np.ndarray
    next_obs: "np.ndarray | None" = None
    t: "np.ndarray | None" = None
    policy_version: "np.ndarray | None" = None
    log_prob: "np.ndarray | None" = None
    value: "np.ndarray | None" = None
    # Sharded sessions: the index (in `Client.addresses`) of the server each transition came from.
    server: "np.ndarray | None" = None
    discount: "np.ndarray | None" = None
    views: "dict[str, np.ndarray]" = field(default_factory=dict)
    key: "np.ndarray | None" = None
    probability: "np.ndarray | None" = None
    table_size: "np.ndarray | None" = None
    weight: "np.ndarray | None" = None
    is_first: "np.ndarray | None" = None
    is_last: "np.ndarray | None" = None
    is_terminal: "np.ndarray | None" = None
    mask: "np.ndarray | None" = None

    def __len__(self) -> int:
        return len(self.reward)


def importance_weights(probability: np.ndarray, table_size: "np.ndarray | int", beta: float) -> np.ndarray:
    """Prioritized replay's importance weights (Schaul et al. 2016): `(table_size * probability) **
    -beta`, divided by the largest, as float32; what the server sends as `Batch.weight` for the
    request's beta, for a learner that anneals beta itself."""
    weights = (np.asarray(table_size, dtype=np.float64) * np.asarray(probability, dtype=np.float64)) ** -float(beta)
    return (weights / weights.max()).astype(np.float32)


# The server's default beta (Schaul et al.'s starting value).
DEFAULT_IMPORTANCE_SAMPLING_EXPONENT = 0.4


@dataclass(frozen=True)
class PriorityUpdate:
    """What `update_priorities` changed: transitions whose priority was replaced, and keys of
    transitions the replay no longer holds (overwritten since they were sampled: skipped)."""

    updated: int
    missing: int

    def __add__(self, other: "PriorityUpdate") -> "PriorityUpdate":
        return PriorityUpdate(self.updated + other.updated, self.missing + other.missing)


def _host(value: Any) -> Any:
    """A torch tensor (on any device: a learner's TD errors) as numpy; anything else as it is."""
    if hasattr(value, "detach") and hasattr(value, "cpu"):
        return value.detach().cpu().numpy()
    return value


def _priority_arrays(batch: Any, priorities: Any) -> "tuple[np.ndarray, np.ndarray]":
    if batch.key is None:
        raise InvalidArgumentError("this batch carries no `key`: update_priorities takes batches of a stream "
                                   "opened with sampler='prioritized'")
    keys = np.asarray(_host(batch.key), dtype=np.int64).reshape(-1)
    values = np.asarray(_host(priorities), dtype=np.float64).reshape(-1)
    if values.shape != keys.shape:
        raise InvalidArgumentError(f"update_priorities needs one priority per transition of the batch ({len(keys)}), "
                                   f"got {values.size}")
    return keys, values


def send_priorities(transport, session_id: str, keys: np.ndarray, priorities: np.ndarray) -> PriorityUpdate:
    """One UpdatePriorities call (the server checks every value first: finite, non-negative)."""
    request = pb.UpdatePrioritiesRequest(session_id=session_id, keys=keys.astype(np.uint64).tolist(),
                                         priorities=priorities.tolist())
    response = transport.call("UpdatePriorities", request)
    return PriorityUpdate(updated=response.updated, missing=response.missing)


class _Prioritized:
    """`update_priorities` for a stream of one server's session."""

    _transport: Any = None
    _session_id: str = ""

    def update_priorities(self, batch: Batch, priorities: Any) -> PriorityUpdate:
        """Replace the priorities of `batch`'s transitions (from this stream, `sampler="prioritized"`;
        a `radserve.torch` TensorBatch too) with `priorities`, one per transition, finite and
        non-negative (numpy or a torch tensor on any device): a learner sends `abs(td_error) + 1e-6`,
        say. New transitions enter at the largest priority set so far."""
        keys, values = _priority_arrays(batch, priorities)
        return send_priorities(self._transport, self._session_id, keys, values)


def make_batch(index: int, arrays: "dict[str, np.ndarray]", order: "list[str] | None" = None) -> Batch:
    """A Batch from its arrays by field name: metadata fields by name, every other one a view (in
    `order` where given, the request's order)."""
    views = {name: array for name, array in arrays.items() if name not in METADATA_FIELDS and name != "server"}
    if order:
        views = {name: views[name] for name in sorted(views, key=lambda name: order.index(name) if name in order else len(order))}
    fields = {name: arrays[name] for name in (*METADATA_FIELDS, "server") if name in arrays}
    for flag in _FLAGS:
        if flag in fields:
            fields[flag] = fields[flag].astype(bool)
    return Batch(index=index, obs=views.get("obs"), next_obs=views.get("next_obs"), views=views, **fields)


def _varint(data: memoryview, position: int) -> "tuple[int, int]":
    result = shift = 0
    while True:
        byte = data[position]
        position += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, position
        shift += 7


class _Chunk:
    __slots__ = ("batch_index", "field", "dtype", "shape", "offset", "field_bytes", "last", "data")

    def __init__(self, message: bytes):
        view = memoryview(message)
        self.batch_index = self.dtype = self.offset = self.field_bytes = 0
        self.field, self.shape, self.last, self.data = "", [], False, view[0:0]
        position, end = 0, len(view)
        while position < end:
            key, position = _varint(view, position)
            number, wire = key >> 3, key & 7
            if wire == 0:
                value, position = _varint(view, position)
                if number == 1:
                    self.batch_index = value
                elif number == 3:
                    self.dtype = value
                elif number == 4:
                    self.shape.append(value)
                elif number == 5:
                    self.offset = value
                elif number == 6:
                    self.field_bytes = value
                elif number == 7:
                    self.last = bool(value)
            elif wire == 2:
                length, position = _varint(view, position)
                payload = view[position : position + length]
                position += length
                if number == 2:
                    self.field = bytes(payload).decode()
                elif number == 4:  # packed shape
                    inner = 0
                    while inner < length:
                        value, inner = _varint(payload, inner)
                        self.shape.append(value)
                elif number == 15:
                    self.data = payload
            elif wire == 1:
                position += 8
            elif wire == 5:
                position += 4
            else:
                raise ValueError(f"unexpected protobuf wire type {wire} in a BatchChunk")


def iterate_batches(stream, error=from_rpc_error) -> Iterator[Batch]:
    """Assemble Batch objects from a stream of raw BatchChunk messages (`error` maps a failed call to
    the error raised)."""
    buffers: "dict[str, tuple[np.ndarray, int, list]]" = {}
    try:
        for message in stream:
            chunk = _Chunk(message)
            entry = buffers.get(chunk.field)
            if entry is None or chunk.offset == 0:
                entry = (np.empty(chunk.field_bytes, dtype=np.uint8), chunk.dtype, chunk.shape)
                buffers[chunk.field] = entry
            target = entry[0]
            target[chunk.offset : chunk.offset + len(chunk.data)] = np.frombuffer(chunk.data, dtype=np.uint8)
            if chunk.last:
                arrays = {name: raw.view(NUMPY_DTYPES[dtype]).reshape(shape) for name, (raw, dtype, shape) in buffers.items()}
                buffers = {}
                yield make_batch(chunk.batch_index, arrays)
    except grpc.RpcError as failure:
        raise error(failure) from None


class BatchStream(_Prioritized):
    """An iterator of Batch objects; `close()` (or leaving a `with` block) cancels the stream and the
    server frees its producer."""

    def __init__(self, call, error=from_rpc_error):
        self._call = call
        self._batches = iterate_batches(call, error)

    def __iter__(self) -> "BatchStream":
        return self

    def __next__(self) -> Batch:
        return next(self._batches)

    def close(self) -> None:
        self._call.cancel()

    def __enter__(self) -> "BatchStream":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


_SHARED_MAGIC = b"radserve-batches"
_END_OF_REQUESTS = None


def map_region(region: "pb.SharedMemoryRegion") -> mmap.mmap:
    """Map the server's batch memory and check that it is the memory the server described."""
    hint = ("shared-memory batches need the learner on the server's host, in its network namespace, as a user "
            "the server allows; use delivery='grpc' otherwise")
    memory, connection = receive_server_memory(
        region.socket, region.token, region.size, _SHARED_MAGIC, "batch memory", hint)
    connection.close()
    return memory


class SharedBatchStream(_Prioritized):
    """An iterator of Batch objects whose observations are read in place from shared memory.

    `obs` and `next_obs` are views of a slot the server owns again once the next batch is taken:
    use (or copy) a batch before asking for the next one. Moving it to a GPU (`radserve.torch`) or
    through any numpy operation that makes a new array is enough. The other fields are the
    stream's own arrays. `close()` (or leaving a `with` block) ends the stream; the server frees the
    memory, and what this process mapped stays readable until its arrays are gone.
    """

    def __init__(self, method, request: "pb.SampleBatchesRequest", error=from_rpc_error):
        self._closed = False
        self._error = error
        self._requests: "queue.SimpleQueue" = queue.SimpleQueue()
        self._requests.put(pb.SharedSampleRequest(start=request))
        self._call = method(iter(self._requests.get, _END_OF_REQUESTS))
        self._held: "int | None" = None
        try:
            first = next(self._call)
        except grpc.RpcError as failure:
            self.close()
            raise error(failure) from None
        try:
            self._memory = map_region(first.region)
        except SharedMemoryError:
            self.close()
            raise
        self.slots = first.region.slots
        self._order = [view.name for view in request.views] or ["obs", "next_obs"]

    def __iter__(self) -> "SharedBatchStream":
        return self

    def __next__(self) -> Batch:
        if self._held is not None:
            self._requests.put(pb.SharedSampleRequest(release=self._held))
            self._held = None
        try:
            message = next(self._call).batch
        except StopIteration:
            self.close()  # ends the request iterator, whose thread would otherwise wait on it forever
            raise
        except grpc.RpcError as failure:
            self.close()
            raise self._error(failure) from None
        arrays = {}
        for name, tensor in message.shared.items():
            dtype = np.dtype(NUMPY_DTYPES[tensor.dtype])
            shape = tuple(tensor.shape)
            count = int(np.prod(shape))
            arrays[name] = np.frombuffer(self._memory, dtype=dtype, count=count, offset=tensor.offset).reshape(shape)
        for name, tensor in message.tensors.items():
            arrays[name] = np.frombuffer(tensor.data, dtype=NUMPY_DTYPES[tensor.dtype]).reshape(tuple(tensor.shape)).copy()
        self._held = message.batch_index
        return make_batch(message.batch_index, arrays, self._order)

    @property
    def closed(self) -> bool:
        """Whether the stream has ended its requests (closed, or run out)."""
        return self._closed

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._requests.put(_END_OF_REQUESTS)
            self._call.cancel()

    def __enter__(self) -> "SharedBatchStream":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def open_batch_stream(transport, request: "pb.SampleBatchesRequest", delivery: str):
    """The batch stream `request` asks one server for, delivered as `delivery` says ("auto": shared
    memory when it can be mapped here, else the gRPC byte stream). Errors in the request are raised
    before the first batch."""

    def shared() -> SharedBatchStream:
        method = transport.channel.stream_stream(
            "/radserve.v1.RadServe/SampleBatchesShared",
            request_serializer=pb.SharedSampleRequest.SerializeToString,
            response_deserializer=pb.SharedSampleResponse.FromString,
        )
        return SharedBatchStream(method, request, transport.error)

    def streamed() -> BatchStream:
        method = transport.channel.unary_stream(
            "/radserve.v1.RadServe/SampleBatches",
            request_serializer=pb.SampleBatchesRequest.SerializeToString,
            response_deserializer=None,  # raw bytes: parsed here without copies
        )
        call = method(request)
        # The server checks the whole request before its stream starts: a refusal arrives instead of
        # the response headers, and ends the call at once.
        call.initial_metadata()
        if call.done() and call.code() != grpc.StatusCode.OK:
            raise transport.error(call) from None
        return BatchStream(call, transport.error)

    stream = transport.negotiate(delivery, shared, streamed)
    stream._transport, stream._session_id = transport, request.session_id
    return stream


_SOURCES = {"replay": pb.SOURCE_REPLAY, "rollout": pb.SOURCE_ROLLOUT}
_SAMPLERS = {"uniform": pb.SAMPLER_UNIFORM, "prioritized": pb.SAMPLER_PRIORITIZED}


def sample_request(session_id: str, batch_size: int, *, augment: str = "none", sharing: str = "reference",
                   prefetch: int = 2, seed: int = 0, min_size: "int | None" = None,
                   samples_per_insert: "float | None" = None, error_buffer: float = 0.0,
                   max_batches: "int | None" = None, chunk_bytes: int = 0, source: str = "replay", epochs: int = 1,
                   per_env_augmentation: bool = False, include_next_obs: "bool | None" = None,
                   views: "Mapping[str, str | View] | None" = None, n_step: "int | None" = None,
                   discount: "float | None" = None, sampler: str = "uniform",
                   priority_exponent: "float | None" = None,
                   importance_sampling_exponent: "float | None" = None,
                   sequence: "int | Sequence | None" = None) -> "pb.SampleBatchesRequest":
    """SampleBatches' request (see `SamplingMixin.sample_batches` for the settings)."""
    if sharing not in SHARING:
        raise InvalidArgumentError(f"sharing must be one of {sorted(SHARING)}, got {sharing!r}")
    if source not in _SOURCES:
        raise InvalidArgumentError(f"source must be one of {sorted(_SOURCES)}, got {source!r}")
    if sampler not in _SAMPLERS:
        raise InvalidArgumentError(f"sampler must be one of {sorted(_SAMPLERS)}, got {sampler!r}")
    named = []
    for name, view in (views or {}).items():
        view = View(view) if isinstance(view, str) else view
        if not isinstance(view, View) or view.of not in _VIEW_OF:
            raise InvalidArgumentError(
                f"views[{name!r}] must be a pipeline's text or a radserve.View with of 'obs' or 'next_obs', got {view!r}")
        named.append(pb.SampleView(name=name, of=_VIEW_OF[view.of], pipeline_text=view.augment, draws=view.draws or ""))
    # With views, the request's own pipeline is left unset (the server refuses it beside views).
    pipeline = {} if named else {"pipeline_text": augment}
    return pb.SampleBatchesRequest(
        session_id=session_id, batch_size=batch_size, sharing=SHARING[sharing],
        prefetch=prefetch, seed=seed, min_size=min_size, samples_per_insert=samples_per_insert,
        error_buffer=error_buffer, max_batches=max_batches, chunk_bytes=chunk_bytes, source=_SOURCES[source],
        epochs=epochs, per_env_augmentation=per_env_augmentation, include_next_obs=include_next_obs,
        views=named, n_step=n_step, discount=discount, sampler=_SAMPLERS[sampler],
        priority_exponent=priority_exponent, importance_sampling_exponent=importance_sampling_exponent,
        sequence=_sequence_request(sequence), **pipeline)


class SamplingMixin:
    """`sample_batches` for a vector env whose session keeps a buffer: each env opens its stream
    (`_open_batches`), one server's or every server's."""

    session_id: str

    def _open_batches(self, request: "pb.SampleBatchesRequest", delivery: str):  # pragma: no cover - the env's
        raise NotImplementedError

    def sample_batches(self, batch_size: int, *, delivery: str = "grpc", **settings: Any):
        """Stream minibatches sampled uniformly from this env's replay buffer and augmented on the
        server: an iterator of `radserve.Batch` (numpy arrays), produced `prefetch` ahead (a
        `radserve.Batches`).

        `augment` is a pipeline in text form (`"crop(84)"`, `"translate(108)|grayscale"`, `"none"`;
        see docs/augmentations.md); `sharing` says whether obs and next_obs share draws
        (`"reference"`: as RAD's code, `"shared"`, `"independent"`). `views` names the outputs
        instead (DrQ's `{"obs": "shift(4)", "obs_aug": "shift(4)", "next_obs": "shift(4)",
        "next_obs_aug": "shift(4)"}`): each a pipeline's text or a `radserve.View`, carried in
        `Batch.views` under its name (see docs/replay.md). `n_step` and `discount` make `reward` the
        n-step return, with `Batch.discount` the bootstrap's factor and `next_obs` the observation
        after the window. `sampler="prioritized"` draws in proportion to priority ** `priority_exponent`
        (default 0.6) and adds `key`, `probability`, `table_size` and `weight` (with
        `importance_sampling_exponent`, default 0.4) to each batch; `stream.update_priorities(batch,
        td_errors)` sets new priorities (see docs/replay.md). `sequence` (a length or a
        `radserve.Sequence`) samples sequences of consecutive steps instead: every array gains a
        time axis and batches carry `is_first`, `is_last`, `is_terminal` and `mask` (R2D2's burn-in
        and period, Dreamer's windows across episodes, SPR's futures). Sampling waits for `min_size`
        transitions (default: one batch) and, with `samples_per_insert` (and `error_buffer`), keeps
        to Reverb's SampleToInsertRatio, counted from `min_size` on, against the envs' inserts.

        `source="rollout"` serves a rollout session's last rollout instead: `epochs` passes, each
        visiting every (t, env) once in a fresh random order (batches carry `t` and `env_index` to
        pair with the values and advantages the learner computed), augmentation drawn per sample or,
        with `per_env_augmentation`, once per env for the whole rollout; the stream then ends.

        `delivery="shared_memory"` is for a learner on the server's host: the server writes the
        observations into memory this process maps and only descriptors travel (no 32 MB through a
        socket); the arrays are then views valid until the next batch is taken (see
        `radserve.SharedBatchStream`). `"auto"` uses shared memory when it can be mapped and the
        gRPC byte stream otherwise; `"grpc"` (the default) always streams the bytes. A sharded env
        draws from every server's replay (`radserve.ShardedBatchStream`).
        Errors in the request are raised before the first batch. `close()` the stream (or use it in a
        `with` block) to stop it early. Other settings: `prefetch`, `seed`, `max_batches`,
        `chunk_bytes`, `include_next_obs`.
        """
        check_delivery(delivery)
        return self._open_batches(sample_request(self.session_id, batch_size, **settings), delivery)
