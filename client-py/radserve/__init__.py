"""radserve: reinforcement-learning simulators served over gRPC.

Public names only; the generated gRPC code lives in the private `radserve._proto` package.
"""

from .batches import Batch, BatchStream, SharedBatchStream
from .client import Client, EnvInfo, SessionInfo, SessionSummary
from .errors import (
    FailedPreconditionError,
    InternalError,
    InvalidArgumentError,
    NotFoundError,
    RadServeError,
    ResourceExhaustedError,
    SharedMemoryError,
    UnavailableError,
)
from .server import LocalServer
from .vector import RemoteVectorEnv

__all__ = [
    "Client", "EnvInfo", "SessionInfo", "SessionSummary", "Batch", "BatchStream", "SharedBatchStream", "RemoteVectorEnv",
    "LocalServer",
    "RadServeError", "NotFoundError", "InvalidArgumentError", "FailedPreconditionError",
    "ResourceExhaustedError", "UnavailableError", "InternalError", "SharedMemoryError",
]
