"""The client's value types: what the server says about its catalog, itself and its sessions.

They depend on nothing else of the client, so that the client, the vector envs and the sharded
sessions all import them from here (none of those imports another to get them).
"""

from dataclasses import dataclass, field
from typing import Any

from gymnasium import spaces

from . import _convert
from ._proto import radserve_pb2 as pb


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
    """its release, e.g. "0.1.0" (`radserve --version`)"""
    api: str
    """the gRPC API it implements, "radserve.v1" """


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
    # The name it was created with ("": none).
    name: str = ""
    # Its server-side actor (radserve.actors.ActingInfo), once a policy was set.
    acting: "Any" = None

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
                # A named session's snapshot on a server that snapshots (`[replay] snapshot_dir`).
                "snapshot": {
                    "restored_transitions": message.replay.snapshot.restored_transitions,
                    "disk_bytes": message.replay.snapshot.disk_bytes,
                    "age_seconds": message.replay.snapshot.age_seconds
                    if message.replay.snapshot.HasField("age_seconds") else None,
                    "pending_frames": message.replay.snapshot.pending_frames,
                }
                if message.replay.HasField("snapshot")
                else None,
            }
            if message.HasField("replay")
            else None,
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
