"""How the client reaches a server that wants TLS and a bearer token (docs/security.md).

Addresses: `host:port` is plain gRPC (h2c), as a server on loopback serves it; `grpcs://host:port`
is TLS (the system's CA certificates unless `tls` or RADSERVE_TLS_CA names a CA); `grpc://host:port` is plain gRPC
spelled out. Other gRPC target forms (`dns:///name:port`) pass through as they are.
"""

import os
from collections import namedtuple
from dataclasses import dataclass
from pathlib import Path

import grpc

from .errors import InvalidArgumentError

#: The environment variable a token is read from when `Client(token=...)` is not given.
TOKEN_VARIABLE = "RADSERVE_TOKEN"
#: The environment variables a TLS channel takes its files from when `Client(tls=...)` is not a
#: TlsConfig (a `grpcs://` address, or tls=True): TlsConfig's fields, each a path.
TLS_VARIABLES = {"ca": "RADSERVE_TLS_CA", "cert": "RADSERVE_TLS_CERT", "key": "RADSERVE_TLS_KEY",
                 "server_name": "RADSERVE_TLS_SERVER_NAME"}


@dataclass(frozen=True)
class TlsConfig:
    """TLS for the channel. Each of `ca`, `cert` and `key` is a PEM file's path or its bytes.

    ca: the CA that signed the server's certificate (None: the system's CA certificates).
    cert, key: this client's certificate and key, for a server that checks clients (mTLS).
    server_name: the name to check the server's certificate against, when it is not the address's
      host (an IP address, a name behind a load balancer).
    """

    ca: "str | os.PathLike | bytes | None" = None
    cert: "str | os.PathLike | bytes | None" = None
    key: "str | os.PathLike | bytes | None" = None
    server_name: "str | None" = None

    @classmethod
    def from_environment(cls) -> "TlsConfig":
        """The TlsConfig that RADSERVE_TLS_CA, RADSERVE_TLS_CERT, RADSERVE_TLS_KEY and
        RADSERVE_TLS_SERVER_NAME describe (each unset or empty: that field's default), as a container
        is given its CA and client certificate (a Kubernetes Secret mounted as files)."""
        return cls(**{field: os.environ.get(variable) or None for field, variable in TLS_VARIABLES.items()})

    def credentials(self) -> grpc.ChannelCredentials:
        if (self.cert is None) != (self.key is None):
            raise InvalidArgumentError("TlsConfig: cert and key come together (a client certificate and its private key)")
        return grpc.ssl_channel_credentials(root_certificates=_pem(self.ca), private_key=_pem(self.key),
                                            certificate_chain=_pem(self.cert))


def _pem(value) -> "bytes | None":
    if value is None or isinstance(value, bytes):
        return value
    return Path(value).read_bytes()


def open_channel(address: str, tls: "TlsConfig | bool | None", token: "str | None", options: list):
    """(the raw channel, the channel calls go through): TLS as the address or `tls` says, and the
    token added to every call's metadata."""
    target, scheme_tls = _target(address)
    if tls is True or (tls is None and scheme_tls):
        tls = TlsConfig.from_environment()
    if tls:
        if tls.server_name:
            options = [*options, ("grpc.ssl_target_name_override", tls.server_name)]
        channel = grpc.secure_channel(target, tls.credentials(), options=options)
    else:
        channel = grpc.insecure_channel(target, options=options)
    if token is None:
        token = os.environ.get(TOKEN_VARIABLE) or None
    if token is None:
        return channel, channel
    return channel, grpc.intercept_channel(channel, _BearerToken(token.strip()))


def _target(address: str) -> "tuple[str, bool]":
    for scheme, secure in (("grpcs://", True), ("grpc://", False), ("https://", True), ("http://", False)):
        if address.startswith(scheme):
            return address[len(scheme):], secure
    return address, False


class _Details(namedtuple("_Details", ("method", "timeout", "metadata", "credentials", "wait_for_ready", "compression")),
               grpc.ClientCallDetails):
    pass


class _BearerToken(grpc.UnaryUnaryClientInterceptor, grpc.UnaryStreamClientInterceptor,
                   grpc.StreamUnaryClientInterceptor, grpc.StreamStreamClientInterceptor):
    """Adds `authorization: Bearer <token>` to every call (a channel-wide call credential that also
    works on plain channels, where gRPC's own access-token credentials are refused)."""

    def __init__(self, token: str):
        self._header = ("authorization", f"Bearer {token}")

    def _with_token(self, details):
        metadata = [*(details.metadata or ()), self._header]
        return _Details(details.method, details.timeout, metadata, details.credentials,
                        getattr(details, "wait_for_ready", None), getattr(details, "compression", None))

    def intercept_unary_unary(self, continuation, details, request):
        return continuation(self._with_token(details), request)

    def intercept_unary_stream(self, continuation, details, request):
        return continuation(self._with_token(details), request)

    def intercept_stream_unary(self, continuation, details, requests):
        return continuation(self._with_token(details), requests)

    def intercept_stream_stream(self, continuation, details, requests):
        return continuation(self._with_token(details), requests)
