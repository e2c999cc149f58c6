"""The client's value types: what the server says about its catalog, itself and its sessions.

They depend on nothing else of the client, so that the client, the vector envs and the sharded
sessions all import them from here (none of those imports another to get them).
"""

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Iterator, Protocol, runtime_checkable

from gymnasium import spaces

from . import _convert
from ._proto import radserve_pb2 as pb

if TYPE_CHECKING:
    from .actors import ActingInfo, LoadedPolicy
    from .batches import Batch, PriorityUpdate


@dataclass(frozen=True)
class EnvInfo:
    """One environment id of the server's catalog, with its spaces under the default options."""

    id: str
    family: str
    observation_space: "spaces.Space | None"
    action_space: "spaces.Space | None"
    default_options: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ServerInfo:
    """What a server says it is (rpc ServerInfo)."""

    address: str
    version: str
    """its release, e.g. "0.2.0" (`radserve --version`)"""
    api: str
    """the gRPC API it implements, "radserve.v1" """


@dataclass(frozen=True)
class SnapshotInfo:
    """A named session's replay snapshot on a server that snapshots (`[replay] snapshot_dir`)."""

    restored_transitions: int
    """transitions restored from it when the session was created"""
    disk_bytes: int
    age_seconds: "float | None"
    """since the snapshot on disk was written (None: none was yet)"""
    pending_frames: int
    """frames recorded since the snapshot on disk was written"""

    @staticmethod
    def from_proto(message: "pb.ReplaySnapshot") -> "SnapshotInfo":
        return SnapshotInfo(restored_transitions=message.restored_transitions, disk_bytes=message.disk_bytes,
                            age_seconds=message.age_seconds if message.HasField("age_seconds") else None,
                            pending_frames=message.pending_frames)


@dataclass(frozen=True)
class ReplayInfo:
    """A session's replay buffer or rollout, as DescribeSession reports it."""

    capacity: int
    size: int
    """transitions that can be sampled now"""
    inserts: int
    samples: int
    batches: int
    batches_per_second: float
    memory_bytes: int
    frames_per_transition: float
    active_streams: int
    rollout_steps: "int | None" = None
    """a rollout's steps per env (None: a replay buffer)"""
    snapshot: "SnapshotInfo | None" = None

    @staticmethod
    def from_proto(message: "pb.ReplayInfo") -> "ReplayInfo":
        return ReplayInfo(
            capacity=message.capacity,
            size=message.size,
            inserts=message.inserts,
            samples=message.samples,
            batches=message.batches,
            batches_per_second=message.batches_per_second,
            memory_bytes=message.memory_bytes,
            frames_per_transition=message.frames_per_transition,
            active_streams=message.active_streams,
            rollout_steps=message.rollout_steps or None,
            snapshot=SnapshotInfo.from_proto(message.snapshot) if message.HasField("snapshot") else None,
        )


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
    replay: "ReplayInfo | None" = None
    # The name it was created with ("": none).
    name: str = ""
    # Its server-side actor, once a policy was set.
    acting: "ActingInfo | None" = None

    @staticmethod
    def from_proto(message: "pb.SessionInfo") -> "SessionInfo":
        from .actors import ActingInfo
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
            replay=ReplayInfo.from_proto(message.replay) if message.HasField("replay") else None,
            name=message.name,
            acting=ActingInfo.from_proto(message.acting) if message.HasField("acting") else None,
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
    # The address of the server that holds it.
    server: str = ""
    # The name it was created with ("": none).
    name: str = ""

    @staticmethod
    def from_proto(message: "pb.SessionSummary", idle_timeout_seconds: float, server: str = "") -> "SessionSummary":
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
            server=server,
            name=message.name,
        )


@runtime_checkable
class Batches(Protocol):
    """What `sample_batches` returns, from one server or several: an iterator of `radserve.Batch`
    that stops early on `close()` (or at the end of a `with` block)."""

    def __iter__(self) -> "Iterator[Batch]": ...

    def __next__(self) -> "Batch": ...

    def close(self) -> None: ...

    def update_priorities(self, batch: "Batch", priorities: Any) -> "PriorityUpdate":
        """Set the priorities of a prioritized batch's transitions (see `Batch`)."""
        ...

    def __enter__(self) -> "Batches": ...

    def __exit__(self, *exc_info: Any) -> Any: ...


@runtime_checkable
class SessionEnv(Protocol):
    """What `Client.make_vec` returns, on one server (`RemoteVectorEnv`) or several
    (`ShardedVectorEnv`): a gymnasium VectorEnv on a server-side session, with the same shapes either
    way. Calls that go to every server return a list in server order (None for a server lost now)."""

    num_envs: int
    session_id: str
    policy_version: int
    """the last policy version this env sent with set_policy (0: none)"""

    def reset(self, *, seed: Any = None, options: "dict | None" = None) -> Any: ...

    def step(self, actions: Any) -> Any: ...

    def describe(self) -> "list[SessionInfo | None]": ...

    def sample_batches(self, batch_size: int, **settings: Any) -> Batches: ...

    def set_policy(self, policy: Any, example_obs: Any = None, **settings: Any) -> "list[LoadedPolicy | None]": ...

    def start_acting(self, **settings: Any) -> "list[ActingInfo | None]": ...

    def stop_acting(self) -> "list[ActingInfo | None]": ...

    def acting(self) -> "list[ActingInfo | None]": ...

    def wait_acting(self, timeout: "float | None" = None, **until: Any) -> "list[ActingInfo | None]": ...

    def close(self, **kwargs: Any) -> None: ...
