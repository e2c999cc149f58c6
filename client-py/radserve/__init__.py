"""radserve: reinforcement-learning simulators served over gRPC.

Public names only. `radserve.proto` holds the generated messages and stubs of the gRPC API
(`radserve.v1`), for callers who speak it directly.
"""

from ._version import __version__
from ._security import TlsConfig
from ._transport import resolve as resolve_addresses
from .batches import Batch, BatchStream, PriorityUpdate, Sequence, SharedBatchStream, View, importance_weights
from .client import Client
from .errors import (
    AlreadyExistsError,
    CancelledError,
    DeadlineExceededError,
    FailedPreconditionError,
    InternalError,
    InvalidArgumentError,
    NotFoundError,
    PermissionDeniedError,
    RadServeError,
    ResourceExhaustedError,
    SharedMemoryError,
    UnauthenticatedError,
    UnavailableError,
    UnimplementedError,
)
from .server import LocalServer
from .sharded import ShardedBatchStream, ShardedVectorEnv
from .actors import ActingInfo, LoadedPolicy
from .types import Batches, EnvInfo, ReplayInfo, ServerInfo, SessionEnv, SessionInfo, SessionSummary, SnapshotInfo
from .vector import RemoteVectorEnv

__all__ = [
    "__version__", "Client", "EnvInfo", "ServerInfo", "SessionInfo", "SessionSummary", "Batch", "BatchStream", "View", "Sequence",
    "SharedBatchStream", "RemoteVectorEnv", "ShardedVectorEnv", "ShardedBatchStream", "LocalServer", "TlsConfig",
    "resolve_addresses", "ActingInfo", "LoadedPolicy", "Batches", "SessionEnv", "ReplayInfo", "SnapshotInfo",
    "PriorityUpdate", "importance_weights", "RadServeError", "NotFoundError", "InvalidArgumentError", "FailedPreconditionError",
    "ResourceExhaustedError", "UnavailableError", "InternalError", "SharedMemoryError",
    "UnauthenticatedError", "PermissionDeniedError", "DeadlineExceededError", "AlreadyExistsError",
    "CancelledError", "UnimplementedError",
]
