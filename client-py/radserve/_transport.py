"""One connection to one radserve server, shared by every part of the client that talks to it.

`Transport` owns the channel and the stub, maps gRPC errors to radserve's (naming the server when a
client has several), negotiates the delivery (shared memory or gRPC) in one place, and remembers the
sessions opened through it so that they are closed when the process exits.
"""

from __future__ import annotations

import atexit
import socket
import time
import weakref
from typing import Callable, TypeVar

import grpc

from ._proto import radserve_pb2 as pb
from ._proto import radserve_pb2_grpc as pb_grpc
from ._security import TlsConfig, _target, open_channel
from .errors import InvalidArgumentError, SharedMemoryError, UnavailableError, from_rpc_error

# Large batches of frames must fit; the server bounds them itself.
CHANNEL_OPTIONS = [("grpc.max_receive_message_length", -1), ("grpc.max_send_message_length", -1)]
DELIVERIES = ("grpc", "shared_memory", "auto")

T = TypeVar("T")

# Transports not yet closed; at exit each closes the sessions opened through it (weak: none is kept alive).
_LIVE: "weakref.WeakSet[Transport]" = weakref.WeakSet()


@atexit.register
def _close_sessions_at_exit() -> None:
    for transport in list(_LIVE):
        transport.close_open_sessions()


def check_delivery(delivery: str) -> None:
    if delivery not in DELIVERIES:
        raise InvalidArgumentError(f"delivery must be one of {DELIVERIES}, got {delivery!r}")


def resolve(addresses: "str | list[str] | tuple[str, ...]") -> "list[str]":
    """The servers an address names: a list (or a comma-separated string, as a command line gives it)
    names each; `dns:///name:port` names every address the name resolves to (a Kubernetes headless
    Service's pods, in a stable order); anything else, one."""
    if isinstance(addresses, str) and "," in addresses:
        addresses = [entry.strip() for entry in addresses.split(",") if entry.strip()]
    if isinstance(addresses, (list, tuple)):
        if not addresses:
            raise InvalidArgumentError("Client needs at least one address")
        return [address for entry in addresses for address in resolve(entry)]
    if not isinstance(addresses, str):
        raise TypeError(f"an address is a string or a list of strings, got {addresses!r}")
    if not addresses.startswith("dns:"):
        return [addresses]
    # dns:///host:port, or dns://authority/host:port (the authority, a DNS server, is not used here).
    target = addresses[len("dns:"):].lstrip("/").split("/")[-1]
    host, _, port = target.rpartition(":")
    if not host or not port.isdigit():
        raise InvalidArgumentError(f"a dns: address is dns:///host:port, got {addresses!r}")
    try:
        found = socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM)
    except socket.gaierror as error:
        raise UnavailableError(f"{addresses}: {host} does not resolve ({error})") from None
    ips = sorted({entry[4][0] for entry in found}, key=lambda ip: (":" in ip, socket.inet_pton(
        socket.AF_INET6 if ":" in ip else socket.AF_INET, ip)))
    return [f"[{ip}]:{port}" if ":" in ip else f"{ip}:{port}" for ip in ips]


class Transport:
    """A channel to one server: its stub, its calls with errors mapped, its delivery negotiation."""

    def __init__(self, address: str, *, token: "str | None" = None, tls: "TlsConfig | bool | None" = None,
                 wait_ready: float = 10.0, name_in_errors: bool = False):
        self.address = address
        # With several servers, every error says which one it came from.
        self._name_in_errors = name_in_errors
        self.raw_channel, self.channel = open_channel(address, tls, token, CHANNEL_OPTIONS)
        self.stub = pb_grpc.RadServeStub(self.channel)
        # Sessions created through this transport and not closed: closed when the process exits
        # normally, so that they do not wait on the server for their lease to expire.
        self.open_sessions: "set[str]" = set()
        _LIVE.add(self)
        if wait_ready:
            try:
                grpc.channel_ready_future(self.raw_channel).result(timeout=wait_ready)
            except grpc.FutureTimeoutError:
                self.close()
                raise UnavailableError(f"no radserve server answered at {address} within {wait_ready} s",
                                       server=address) from None

    @property
    def target(self) -> str:
        return _target(self.address)[0]

    def serving(self, timeout: float) -> "str | None":
        """None when the server's grpc.health.v1 answers SERVING within `timeout` s (waiting for the
        connection meanwhile); otherwise what it answered or why it did not."""
        check = self.channel.unary_unary(_HEALTH_CHECK, request_serializer=_empty_health_request,
                                         response_deserializer=_health_status)
        try:
            status = check(None, timeout=timeout, wait_for_ready=True)
        except grpc.RpcError as error:
            code = error.code() if hasattr(error, "code") else None
            details = error.details() if hasattr(error, "details") else str(error)
            return f"{code.name if code else 'no answer'}: {details}"
        return None if status == _SERVING else _STATUS_NAMES.get(status, f"status {status}")

    def error(self, error: grpc.RpcError):
        """The radserve error for a failed call (naming this server when the client has several)."""
        mapped = from_rpc_error(error)
        mapped.server = self.address
        if self._name_in_errors:
            mapped.args = (f"server {self.address}: {mapped.args[0]}",)
        return mapped

    def call(self, method: str, request, **kwargs):
        try:
            return getattr(self.stub, method)(request, **kwargs)
        except grpc.RpcError as error:
            raise self.error(error) from None

    def future(self, method: str, request):
        """A unary call sent now; `result(future)` waits for it."""
        return getattr(self.stub, method).future(request)

    def result(self, future):
        try:
            return future.result()
        except grpc.RpcError as error:
            raise self.error(error) from None

    def create_session(self, request: "pb.CreateSessionRequest") -> "pb.SessionInfo":
        info = self.call("CreateSession", request)
        self.open_sessions.add(info.session_id)
        return info

    def close_session(self, session_id: str, timeout: "float | None" = None, discard_snapshot: bool = False) -> None:
        self.open_sessions.discard(session_id)
        self.call("CloseSession", pb.CloseSessionRequest(session_id=session_id, discard_snapshot=discard_snapshot),
                  timeout=timeout)

    @staticmethod
    def negotiate(delivery: str, shared: Callable[[], T], fallback: Callable[[], T]) -> T:
        """`shared()` for shared-memory delivery, `fallback()` for gRPC; "auto" falls back when the
        memory cannot be handed over (another host, namespace or user) and "shared_memory" raises."""
        check_delivery(delivery)
        if delivery != "grpc":
            try:
                return shared()
            except SharedMemoryError:
                if delivery == "shared_memory":
                    raise
        return fallback()

    def close_open_sessions(self, timeout: float = 2.0) -> None:
        for session_id in list(self.open_sessions):
            self.open_sessions.discard(session_id)
            try:
                self.stub.CloseSession(pb.CloseSessionRequest(session_id=session_id), timeout=timeout)
            except grpc.RpcError as error:
                # NOT_FOUND: already gone (closed, reaped). A server that is gone or does not answer
                # frees the sessions itself (shutdown, leases): do not wait on it once per session.
                if error.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                    self.open_sessions.clear()
                    return

    def close(self) -> None:
        _LIVE.discard(self)
        self.raw_channel.close()


# grpc.health.v1 (https://github.com/grpc/grpc/blob/master/doc/health-checking.md), the protocol
# kubelet probes and `radserve healthcheck` speak. Its two messages have one field each: the request's
# `service` (empty: the server as a whole, which proto3 encodes as no bytes at all) and the response's
# enum `status` (field 1, a varint). They are coded here rather than through grpcio-health-checking,
# which would be a dependency of the client for these two fields.
_HEALTH_CHECK = "/grpc.health.v1.Health/Check"
_SERVING = 1
_STATUS_NAMES = {0: "UNKNOWN", 1: "SERVING", 2: "NOT_SERVING", 3: "SERVICE_UNKNOWN"}


def _empty_health_request(_request) -> bytes:
    return b""


def _health_status(response: bytes) -> int:
    """`HealthCheckResponse.status`: field 1 as a varint (0, UNKNOWN, when absent)."""
    status, shift, index = 0, 0, 0
    while index < len(response):
        tag = response[index]
        index += 1
        if tag != 0x08:  # not field 1 as a varint: nothing else is in this message
            break
        status, shift = 0, 0
        while index < len(response):
            byte = response[index]
            index += 1
            status |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                break
    return status


def wait_serving(transports: "list[Transport]", timeout: float, *, first_backoff: float = 0.25,
                 max_backoff: float = 5.0) -> None:
    """Waits until every server answers SERVING on grpc.health.v1, asking again with exponential
    backoff (a server still starting, or building its catalog, answers NOT_SERVING or nothing);
    raises UnavailableError naming each server that did not within `timeout` s, and why."""
    deadline = time.monotonic() + timeout
    waiting = {transport.address: "not asked" for transport in transports}
    backoff = first_backoff
    while True:
        for transport in transports:
            if transport.address in waiting:
                left = deadline - time.monotonic()
                answer = transport.serving(max(0.05, min(left, 10.0)))
                if answer is None:
                    del waiting[transport.address]
                else:
                    waiting[transport.address] = answer
        if not waiting:
            return
        left = deadline - time.monotonic()
        if left <= 0:
            named = "; ".join(f"{address}: {why}" for address, why in waiting.items())
            raise UnavailableError(f"{len(waiting)} of {len(transports)} radserve servers did not answer SERVING "
                                   f"within {timeout} s ({named})", server=next(iter(waiting)))
        time.sleep(min(backoff, left))
        backoff = min(backoff * 2, max_backoff)

