"""radserve: reinforcement-learning simulators served over gRPC.

Public names only; the generated gRPC code lives in the private `radserve._proto` package.
"""

from ._version import __version__
from .batches import Batch, BatchStream, SharedBatchStream
from .client import Client, EnvInfo, ServerInfo, SessionInfo, SessionSummary
from .errors import (
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
)
from ._security import TlsConfig
from .server import LocalServer
from .sharded import ShardedBatchStream, ShardedVectorEnv
from .vector import RemoteVectorEnv

__all__ = [
    "__version__", "Client", "EnvInfo", "ServerInfo", "SessionInfo", "SessionSummary", "Batch", "BatchStream", "SharedBatchStream", "RemoteVectorEnv",
    "ShardedVectorEnv", "ShardedBatchStream", "LocalServer", "TlsConfig",
    "RadServeError", "NotFoundError", "InvalidArgumentError", "FailedPreconditionError",
    "ResourceExhaustedError", "UnavailableError", "InternalError", "SharedMemoryError",
    "UnauthenticatedError", "PermissionDeniedError",
]
