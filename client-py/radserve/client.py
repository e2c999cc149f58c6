"""The radserve client: environments listed, sessions created, vector environments handed out."""

import atexit
import weakref
from dataclasses import dataclass, field
from typing import Any

import grpc
from gymnasium import spaces

from . import _convert
from ._security import TlsConfig, open_channel
from ._proto import radserve_pb2 as pb
from ._proto import radserve_pb2_grpc as pb_grpc
from .errors import SharedMemoryError, from_rpc_error

# Large batches of frames must fit; the server bounds them itself.
_CHANNEL_OPTIONS = [("grpc.max_receive_message_length", -1), ("grpc.max_send_message_length", -1)]


@dataclass(frozen=True)
class EnvInfo:
    """One environment id of the server's catalog, with its spaces under the default options."""

    id: str
    family: str
    observation_space: "spaces.Space | None"
    action_space: "spaces.Space | None"
    default_options: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SessionInfo:
    session_id: str
    env_id: str
    num_envs: int
    seed: int
    options: dict
    observation_space: spaces.Space
    action_space: spaces.Space
    frame_stack: int
    autoreset_mode: str
    total_env_steps: int
    episodes_completed: int
    replay: "dict | None" = None

    @staticmethod
    def from_proto(message: "pb.SessionInfo") -> "SessionInfo":
        return SessionInfo(
            session_id=message.session_id,
            env_id=message.env_id,
            num_envs=message.num_envs,
            seed=message.seed,
            options={k: _convert.from_option_value(v) for k, v in message.options.items()},
            observation_space=_convert.to_space(message.observation_space),
            action_space=_convert.to_space(message.action_space),
            frame_stack=message.frame_stack,
            autoreset_mode=message.autoreset_mode,
            total_env_steps=message.total_env_steps,
            episodes_completed=message.episodes_completed,
            replay={
                "capacity": message.replay.capacity,
                "size": message.replay.size,
                "inserts": message.replay.inserts,
                "samples": message.replay.samples,
                "batches": message.replay.batches,
                "batches_per_second": message.replay.batches_per_second,
                "memory_bytes": message.replay.memory_bytes,
                "frames_per_transition": message.replay.frames_per_transition,
                "active_streams": message.replay.active_streams,
                "rollout_steps": message.replay.rollout_steps or None,
            }
            if message.HasField("replay")
            else None,
        )


@dataclass(frozen=True)
class SessionSummary:
    """One open session as `Client.list_sessions()` reports it."""

    session_id: str
    env_id: str
    num_envs: int
    memory_bytes: int
    # The principal that created it ("local" on a server without authentication).
    owner: str
    idle_seconds: float
    open_streams: int
    age_seconds: float
    idle_timeout_seconds: float

    @staticmethod
    def from_proto(message: "pb.SessionSummary", idle_timeout_seconds: float) -> "SessionSummary":
        return SessionSummary(
            session_id=message.session_id,
            env_id=message.env_id,
            num_envs=message.num_envs,
            memory_bytes=message.memory_bytes,
            owner=message.owner,
            idle_seconds=message.idle_seconds,
            open_streams=message.open_streams,
            age_seconds=message.age_seconds,
            idle_timeout_seconds=idle_timeout_seconds,
        )


# Clients not yet closed; at exit each closes the sessions it created (weak: no client is kept alive).
_LIVE_CLIENTS: "weakref.WeakSet[Client]" = weakref.WeakSet()


@atexit.register
def _close_sessions_at_exit() -> None:
    for client in list(_LIVE_CLIENTS):
        client._close_open_sessions()


class Client:
    """A connection to one radserve server.

    >>> client = radserve.Client("127.0.0.1:50051")
    >>> envs = client.make_vec("dmc/cheetah-run", num_envs=8, seed=1)

    A server that requires them gets TLS and a bearer token:

    >>> client = radserve.Client("grpcs://radserve-0.radserve:50051", token=os.environ["RADSERVE_TOKEN"],
    ...                          tls=radserve.TlsConfig(ca="ca.pem"))

    `token` defaults to the RADSERVE_TOKEN environment variable; `tls` to TLS with the system's CA
    certificates for a `grpcs://` address and to none otherwise (`True`: TLS with the system's CAs).
    """

    def __init__(self, address: str, *, token: "str | None" = None, tls: "TlsConfig | bool | None" = None,
                 wait_ready: float = 10.0):
        self.address = address
        self._raw_channel, self._channel = open_channel(address, tls, token, _CHANNEL_OPTIONS)
        self._stub = pb_grpc.RadServeStub(self._channel)
        # Sessions this client created and has not closed: closed when the process exits normally,
        # so that they do not wait on the server for their lease to expire.
        self._open_sessions: "set[str]" = set()
        _LIVE_CLIENTS.add(self)
        if wait_ready:
            try:
                grpc.channel_ready_future(self._raw_channel).result(timeout=wait_ready)
            except grpc.FutureTimeoutError:
                self._raw_channel.close()
                from .errors import UnavailableError

                raise UnavailableError(f"no radserve server answered at {address} within {wait_ready} s") from None

    def _call(self, method: str, request, **kwargs):
        try:
            return getattr(self._stub, method)(request, **kwargs)
        except grpc.RpcError as error:
            raise from_rpc_error(error) from None

    def list_envs(self, prefix: str = "") -> "list[EnvInfo]":
        """Every environment id the server hosts (optionally those starting with `prefix`)."""
        response = self._call("ListEnvs", pb.ListEnvsRequest(prefix=prefix))
        return [
            EnvInfo(
                id=env.id,
                family=env.family,
                observation_space=_convert.to_space(env.observation_space) if env.HasField("observation_space") else None,
                action_space=_convert.to_space(env.action_space) if env.HasField("action_space") else None,
                default_options={k: _convert.from_option_value(v) for k, v in env.default_options.items()},
            )
            for env in response.envs
        ]

    def make_vec(
        self,
        env_id: str,
        num_envs: int = 1,
        seed: int = 0,
        *,
        stream: bool = False,
        delivery: str = "grpc",
        replay_capacity: "int | None" = None,
        rollout_steps: "int | None" = None,
        observation_view: str = "",
        autoreset_mode: "str | Any" = "SameStep",
        channels_last: bool = False,
        **options: Any,
    ):
        """Creates a session of `num_envs` environments and returns it as a gymnasium VectorEnv.

        `autoreset_mode` is gymnasium's (`gymnasium.vector.AutoresetMode` or its value): "SameStep"
        (the default: the ending step returns the next episode's first observation, the last one in
        `infos["final_obs"]`), "NextStep" (gymnasium's default, which its observation wrappers need:
        the ending step returns the last observation, the next step the first one) or "Disabled"
        (ended envs wait for `reset(options={"reset_mask": mask})`).

        Environment i is seeded with `seed + i`. `options` override the env's defaults (see
        `list_envs()[...].default_options`), e.g. `pixels=False`, `frame_stack=3`, `num_levels=200`.
        With `stream=True`, reset and step go over one bidirectional stream instead of unary calls.
        `delivery="shared_memory"` acts through memory shared with a server on this host (no message
        per step; raises SharedMemoryError elsewhere), `"auto"` does so when it can and uses gRPC
        otherwise; the env's `delivery` attribute says which it got.
        With `replay_capacity`, the server records every transition into a replay buffer of that many
        transitions, to be sampled with `sample_batches(envs.session_id, ...)`; with `rollout_steps`,
        it keeps the last that many steps of every env as a rollout (`source="rollout"`).
        `observation_view="center_crop(84)"` (or `"center_translate(108)"`) returns observations
        through RAD's evaluation view, matching what the learner trains on; replay keeps raw frames.
        `channels_last=True` returns image observations as `[H, W, C]` (gymnasium's pixel layout, which
        `gymnasium.wrappers.vector.GrayscaleObservation` needs) instead of the server's `[C, H, W]`.
        """
        from .vector import RemoteVectorEnv

        request = pb.CreateSessionRequest(
            env_id=env_id,
            num_envs=num_envs,
            seed=seed,
            options={name: _convert.option_value(value) for name, value in options.items()},
            replay=pb.ReplayOptions(capacity=replay_capacity or 0, rollout_steps=rollout_steps or 0)
            if replay_capacity or rollout_steps
            else None,
            observation_view=observation_view,
        )
        info = SessionInfo.from_proto(self._call("CreateSession", request))
        self._open_sessions.add(info.session_id)
        try:
            return RemoteVectorEnv(self, info, stream=stream, delivery=delivery, autoreset_mode=autoreset_mode,
                                   channels_last=channels_last)
        except BaseException:
            self.close_session(info.session_id)  # the session would otherwise outlive the failed env
            raise

    def sample_batches(
        self,
        session_id: str,
        batch_size: int,
        *,
        augment: str = "none",
        sharing: str = "reference",
        prefetch: int = 2,
        seed: int = 0,
        min_size: "int | None" = None,
        samples_per_insert: "float | None" = None,
        error_buffer: float = 0.0,
        max_batches: "int | None" = None,
        chunk_bytes: int = 0,
        source: str = "replay",
        epochs: int = 1,
        per_env_augmentation: bool = False,
        include_next_obs: "bool | None" = None,
        repeat_first_batch: bool = False,
        delivery: str = "grpc",
    ):
        """Stream minibatches sampled uniformly from the session's replay buffer and augmented on
        the server: an iterator of `radserve.Batch` (numpy arrays), produced `prefetch` ahead.

        `augment` is a pipeline in text form (`"crop(84)"`, `"translate(108)|grayscale"`, `"none"`;
        see docs/augmentations.md); `sharing` says whether obs and next_obs share draws
        (`"reference"`: as RAD's code, `"shared"`, `"independent"`). Sampling waits for `min_size`
        transitions (default: one batch) and, with `samples_per_insert`, for acting to keep up.

        `source="rollout"` serves a rollout session's last rollout instead: `epochs` passes, each
        visiting every (t, env) once in a fresh random order (batches carry `t` and `env_index` to
        pair with the values and advantages the learner computed), augmentation drawn per sample or,
        with `per_env_augmentation`, once per env for the whole rollout; the stream then ends.
        `repeat_first_batch` is for benchmarks: the first batch's bytes are sent again and again.

        `delivery="shared_memory"` is for a learner on the server's host: the server writes the
        observations into memory this process maps and only descriptors travel (no 32 MB through a
        socket); the arrays are then views valid until the next batch is taken (see
        `radserve.SharedBatchStream`). `"auto"` uses shared memory when it can be mapped and the
        gRPC byte stream otherwise; `"grpc"` (the default) always streams the bytes.
        Errors in the request are raised before the first batch. `close()` the stream (or use it in a
        `with` block) to stop it early.
        """
        from .batches import SHARING, BatchStream, SharedBatchStream

        deliveries = ("grpc", "shared_memory", "auto")
        if delivery not in deliveries:
            raise ValueError(f"delivery must be one of {deliveries}, got {delivery!r}")
        if sharing not in SHARING:
            raise ValueError(f"sharing must be one of {sorted(SHARING)}, got {sharing!r}")
        sources = {"replay": pb.SOURCE_REPLAY, "rollout": pb.SOURCE_ROLLOUT}
        if source not in sources:
            raise ValueError(f"source must be one of {sorted(sources)}, got {source!r}")
        request = pb.SampleBatchesRequest(
            session_id=session_id,
            batch_size=batch_size,
            pipeline_text=augment,
            sharing=SHARING[sharing],
            prefetch=prefetch,
            seed=seed,
            min_size=min_size,
            samples_per_insert=samples_per_insert,
            error_buffer=error_buffer,
            max_batches=max_batches,
            chunk_bytes=chunk_bytes,
            source=sources[source],
            epochs=epochs,
            per_env_augmentation=per_env_augmentation,
            include_next_obs=include_next_obs,
            repeat_first_batch=repeat_first_batch,
        )
        if delivery != "grpc":
            shared = self._channel.stream_stream(
                "/radserve.v1.RadServe/SampleBatchesShared",
                request_serializer=pb.SharedSampleRequest.SerializeToString,
                response_deserializer=pb.SharedSampleResponse.FromString,
            )
            try:
                return SharedBatchStream(shared, request)
            except SharedMemoryError:
                if delivery == "shared_memory":
                    raise
        method = self._channel.unary_stream(
            "/radserve.v1.RadServe/SampleBatches",
            request_serializer=pb.SampleBatchesRequest.SerializeToString,
            response_deserializer=None,  # raw bytes: radserve.batches parses them without copies
        )
        call = method(request)
        # The server checks the whole request before its stream starts: a refusal arrives instead of
        # the response headers, and ends the call at once.
        call.initial_metadata()
        if call.done() and call.code() != grpc.StatusCode.OK:
            raise from_rpc_error(call) from None
        return BatchStream(call)

    def describe_session(self, session_id: str) -> SessionInfo:
        return SessionInfo.from_proto(self._call("DescribeSession", pb.DescribeSessionRequest(session_id=session_id)))

    def close_session(self, session_id: str) -> None:
        self._open_sessions.discard(session_id)
        self._call("CloseSession", pb.CloseSessionRequest(session_id=session_id))

    def list_sessions(self) -> "list[SessionSummary]":
        """Every session open on the server (all clients'), oldest first: what each holds and how
        long it has been idle. The server closes a session idle for longer than its
        `limits.session_idle_timeout_s` (`SessionSummary.idle_timeout_seconds`)."""
        response = self._call("ListSessions", pb.ListSessionsRequest())
        return [SessionSummary.from_proto(s, response.idle_timeout_seconds) for s in response.sessions]

    def _close_open_sessions(self, timeout: float = 2.0) -> None:
        for session_id in list(self._open_sessions):
            self._open_sessions.discard(session_id)
            try:
                self._stub.CloseSession(pb.CloseSessionRequest(session_id=session_id), timeout=timeout)
            except grpc.RpcError as error:
                # NOT_FOUND: already gone (closed, reaped). A server that is gone or does not answer
                # frees the sessions itself (shutdown, leases): do not wait on it once per session.
                if error.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                    self._open_sessions.clear()
                    return

    def close(self) -> None:
        _LIVE_CLIENTS.discard(self)
        self._raw_channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
