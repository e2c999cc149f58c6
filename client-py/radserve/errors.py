"""Errors raised by the radserve client: one class per kind of server answer, all RadServeError."""

import grpc


class RadServeError(Exception):
    """A call to a radserve server failed. `code` is the gRPC status code, `details` its message,
    `server` the address of the server that answered (or did not)."""

    def __init__(self, message: str, code: "grpc.StatusCode | None" = None, *, server: "str | None" = None):
        super().__init__(message)
        self.code = code
        self.details = message
        self.server = server


class NotFoundError(RadServeError):
    """Unknown environment id (the message names close matches) or unknown session."""


class InvalidArgumentError(RadServeError, ValueError):
    """The request does not fit: action shape/dtype/bounds, option names or values, seeds."""


class AlreadyExistsError(RadServeError):
    """The caller already has a live session of this name (`make_vec(name=...)`): close it first."""


class FailedPreconditionError(RadServeError):
    """The session is not in a state to take the request (e.g. Step before Reset)."""


class ResourceExhaustedError(RadServeError):
    """A server limit would be exceeded (sessions, environments)."""


class UnavailableError(RadServeError):
    """The server or its simulator workers cannot be reached, or it is shutting down. With several
    servers, `server` names the one lost."""


class InternalError(RadServeError):
    """A simulator failed in a way that is not the caller's fault."""


class UnauthenticatedError(RadServeError):
    """The server requires a bearer token and got none it accepts (Client(token=...), RADSERVE_TOKEN)."""


class PermissionDeniedError(RadServeError):
    """The token is known, but its principal may not make this call (a monitor token acting)."""


class DeadlineExceededError(RadServeError):
    """The call's deadline passed before the server answered (a timeout given to the call, or the
    server's own limit on a call that waits, such as a worker that does not answer in time)."""


class CancelledError(RadServeError):
    """The call was cancelled before it completed (by this client, or by the server when it
    shut down or the stream's peer went away)."""


class UnimplementedError(RadServeError):
    """The server does not implement the call or the option (an older server, or a request that
    radserve does not support, named in the message)."""


class SharedMemoryError(RadServeError):
    """Shared memory (minibatches or shared stepping) cannot be used here: the server's memory could
    not be handed over (the client is on another host, in another network namespace, or runs as a
    user the server does not allow)."""


_BY_CODE = {
    grpc.StatusCode.NOT_FOUND: NotFoundError,
    grpc.StatusCode.INVALID_ARGUMENT: InvalidArgumentError,
    grpc.StatusCode.FAILED_PRECONDITION: FailedPreconditionError,
    grpc.StatusCode.ALREADY_EXISTS: AlreadyExistsError,
    grpc.StatusCode.RESOURCE_EXHAUSTED: ResourceExhaustedError,
    grpc.StatusCode.UNAVAILABLE: UnavailableError,
    grpc.StatusCode.INTERNAL: InternalError,
    grpc.StatusCode.UNAUTHENTICATED: UnauthenticatedError,
    grpc.StatusCode.PERMISSION_DENIED: PermissionDeniedError,
    grpc.StatusCode.DEADLINE_EXCEEDED: DeadlineExceededError,
    grpc.StatusCode.CANCELLED: CancelledError,
    grpc.StatusCode.UNIMPLEMENTED: UnimplementedError,
}


def from_rpc_error(error: grpc.RpcError) -> RadServeError:
    code = error.code() if hasattr(error, "code") else None
    details = error.details() if hasattr(error, "details") else str(error)
    cls = _BY_CODE.get(code, RadServeError)
    return cls(details or str(code), code)


_BY_NUMBER = {code.value[0]: code for code in grpc.StatusCode}


def from_status(number: int, message: str) -> RadServeError:
    """The error for a status that came outside gRPC (the shared-stepping channel)."""
    code = _BY_NUMBER.get(number)
    return _BY_CODE.get(code, RadServeError)(message or str(code), code)
