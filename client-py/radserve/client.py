"""The radserve client: environments listed, sessions created, vector environments handed out."""

import warnings
import weakref
from typing import Any

from . import _convert
from ._proto import radserve_pb2 as pb
from ._security import TlsConfig
from ._transport import Transport, check_delivery, resolve, wait_serving
from .batches import open_batch_stream, sample_request
from .errors import InvalidArgumentError, RadServeError
from .sharded import SERVER_LOSS, ShardedVectorEnv
from .types import Batches, EnvInfo, ServerInfo, SessionEnv, SessionInfo, SessionSummary
from .vector import open_vector_env

__all__ = ["Client", "EnvInfo", "ServerInfo", "SessionInfo", "SessionSummary"]


class Client:
    """A connection to one radserve server, or to several that serve one learner together.

    >>> client = radserve.Client("127.0.0.1:50051")
    >>> envs = client.make_vec("dmc/cheetah-run", num_envs=8, seed=1)

    Several servers (a list, or `dns:///name:port` for every address a name resolves to, such as a
    Kubernetes headless Service) make sharded sessions: `make_vec` spreads the envs over the servers
    and `envs.sample_batches` draws from every server's replay (see `radserve.ShardedVectorEnv`).
    Either way `make_vec` returns a `radserve.SessionEnv`, with the same shapes:

    >>> client = radserve.Client(["radserve-0.radserve:50051", "radserve-1.radserve:50051"])
    >>> client = radserve.Client("dns:///radserve.training.svc.cluster.local:50051")

    A server that requires them gets TLS and a bearer token:

    >>> client = radserve.Client("grpcs://radserve-0.radserve:50051", token=os.environ["RADSERVE_TOKEN"],
    ...                          tls=radserve.TlsConfig(ca="ca.pem"))

    `token` defaults to the RADSERVE_TOKEN environment variable; `tls` to TLS for a `grpcs://`
    address and to none otherwise (`True`: TLS), with the files RADSERVE_TLS_CA, RADSERVE_TLS_CERT
    and RADSERVE_TLS_KEY name (`TlsConfig.from_environment()`; the system's CAs when unset).
    `on_server_loss` is what a sharded session does when one of its servers stops answering:
    "raise" (the default: `UnavailableError` naming the server) or "continue" (act and sample on the
    others; see `ShardedVectorEnv`). `reconnect_backoff` is the first wait (s) before trying a lost
    server again, doubled after each failed try up to `reconnect_backoff_max`.

    `wait_ready` (s) is how long a server has to accept the connection. A learner started beside its
    servers (a Kubernetes Job, a Compose service) gives `wait_ready_s` instead: every server must
    answer SERVING on grpc.health.v1 (a server reports NOT_SERVING until its catalog is built), asked
    again with exponential backoff up to 5 s; past `wait_ready_s` the Client raises
    `UnavailableError` naming each server that did not and what it last answered.
    """

    def __init__(self, address: "str | list[str]", *, token: "str | None" = None,
                 tls: "TlsConfig | bool | None" = None, wait_ready: float = 10.0, wait_ready_s: "float | None" = None,
                 on_server_loss: str = "raise", reconnect_backoff: float = 1.0, reconnect_backoff_max: float = 30.0):
        if on_server_loss not in SERVER_LOSS:
            raise InvalidArgumentError(f"on_server_loss must be one of {SERVER_LOSS}, got {on_server_loss!r}")
        self.addresses = resolve(address)
        if len(set(self.addresses)) != len(self.addresses):
            raise InvalidArgumentError(f"each server is named once, got {self.addresses}")
        self.address = address if isinstance(address, str) else self.addresses[0]
        self.on_server_loss = on_server_loss
        self.reconnect_backoff = (float(reconnect_backoff), float(reconnect_backoff_max))
        several = len(self.addresses) > 1
        self._transports: "list[Transport]" = []
        try:
            for server in self.addresses:
                self._transports.append(Transport(server, token=token, tls=tls,
                                                  wait_ready=0 if wait_ready_s is not None else wait_ready,
                                                  name_in_errors=several))
            if wait_ready_s is not None:
                wait_serving(self._transports, wait_ready_s)
        except BaseException:
            self.close()
            raise
        # Sharded sessions of this client by id (weak: a sharded env no one holds is gone).
        self._sharded: "weakref.WeakValueDictionary[str, Any]" = weakref.WeakValueDictionary()

    @property
    def transports(self) -> "list[Transport]":
        """One per server, in the order given (resolved)."""
        return list(self._transports)

    @property
    def _transport(self) -> Transport:
        return self._transports[0]

    def _for_session(self, session_id: str) -> Transport:
        """The server that holds a (plain) session: the one that created it here, else the first
        that knows it."""
        for transport in self._transports:
            if session_id in transport.open_sessions:
                return transport
        if len(self._transports) > 1:
            for transport in self._transports:
                try:
                    transport.call("DescribeSession", pb.DescribeSessionRequest(session_id=session_id))
                    return transport
                except RadServeError:
                    continue
        return self._transport

    def server_info(self) -> "list[ServerInfo]":
        """What each server is, in the order of the servers. Answers before the server's catalog is
        ready (unlike `list_envs`)."""
        infos = []
        for transport in self._transports:
            response = transport.call("ServerInfo", pb.ServerInfoRequest())
            infos.append(ServerInfo(address=transport.address, version=response.version, api=response.api))
        return infos

    def list_envs(self, prefix: str = "") -> "list[EnvInfo]":
        """Every environment id the server hosts (optionally those starting with `prefix`)."""
        response = self._transport.call("ListEnvs", pb.ListEnvsRequest(prefix=prefix))
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
        autoreset_mode: "str | Any | None" = None,
        channels_last: bool = False,
        name: str = "",
        **options: Any,
    ) -> SessionEnv:
        """Creates a session of `num_envs` environments and returns it as a gymnasium VectorEnv.

        `autoreset_mode` is gymnasium's (`gymnasium.vector.AutoresetMode` or its value): "NextStep"
        (the default, as gymnasium's, which its observation wrappers need: the ending step returns
        the last observation, the next step the first one and ignores that env's action), "SameStep"
        (the ending step returns the next episode's first observation, the last one in
        `infos["final_obs"]`: no step is spent on a reset; radserve's learners use it, and it is the
        only mode, and the default, of a session with `batch_size` below `num_envs`) or "Disabled"
        (ended envs wait for `reset(options={"reset_mask": mask})`).

        Environment i is seeded with `seed + i`. `options` override the env's defaults (see
        `list_envs()[...].default_options`), e.g. `pixels=False`, `frame_stack=3`, `num_levels=200`.
        With `stream=True`, reset and step go over one bidirectional stream instead of unary calls.
        `delivery="shared_memory"` steps through memory shared with a server on this host (no message
        per step; raises SharedMemoryError elsewhere), `"auto"` does so when it can and uses gRPC
        otherwise; the env's `delivery` attribute says which it got.
        With `replay_capacity`, the server records every transition into a replay buffer of that many
        transitions, to be sampled with `envs.sample_batches(batch_size, ...)`; with `rollout_steps`,
        it keeps the last that many steps of every env as a rollout (`source="rollout"`).
        `observation_view="center_crop(84)"` (or `"center_translate(108)"`) returns observations
        through RAD's evaluation view, matching what the learner trains on; replay keeps raw frames.
        `channels_last=True` returns image observations as `[H, W, C]` (gymnasium's pixel layout, which
        `gymnasium.wrappers.vector.GrayscaleObservation` needs) instead of the server's `[C, H, W]`.
        `name` names the session (unique among this principal's live sessions on each server:
        `AlreadyExistsError` otherwise). On a server with `[replay] snapshot_dir` set, a named
        session's replay is snapshotted to disk, and a session created under the same name (same
        env, num_envs, options and capacity), after a restart too, starts with it restored; a sharded
        session that gets a lost server back (`on_server_loss="continue"`) gets its replay back with it.
        """
        request = pb.CreateSessionRequest(
            env_id=env_id,
            num_envs=num_envs,
            seed=seed,
            options={name: _convert.option_value(value) for name, value in options.items()},
            replay=pb.ReplayOptions(capacity=replay_capacity or 0, rollout_steps=rollout_steps or 0)
            if replay_capacity or rollout_steps
            else None,
            observation_view=observation_view,
            name=name,
        )
        settings = dict(stream=stream, delivery=delivery, autoreset_mode=autoreset_mode, channels_last=channels_last)
        check_delivery(delivery)
        if len(self._transports) > 1:
            if options.get("batch_size"):
                raise InvalidArgumentError(
                    "batch_size (EnvPool's asynchronous mode) is for a session on one server; a client of "
                    f"{len(self._transports)} servers steps its envs together (leave batch_size at 0)")

            envs = ShardedVectorEnv(self.transports, request, on_server_loss=self.on_server_loss,
                                    reconnect_backoff=self.reconnect_backoff, **settings)
            self._sharded[envs.session_id] = envs
            return envs
        return open_vector_env(self._transport, request, **settings)

    def sample_batches(self, session_id: str, batch_size: int, *, delivery: str = "grpc", **settings: Any) -> Batches:
        """`envs.sample_batches(batch_size, ...)` by session id: the same stream (see
        `RemoteVectorEnv.sample_batches` for the settings). Deprecated since 0.2.0, kept through 0.2:
        sample from the env, which needs no id (a sharded env's id was a synthetic `sharded-...`
        only this call resolved)."""
        warnings.warn("Client.sample_batches(session_id, ...) is deprecated since radserve 0.2.0: use "
                      "envs.sample_batches(batch_size, ...)", DeprecationWarning, stacklevel=2)
        sharded = self._sharded.get(session_id)
        if sharded is not None:
            return sharded.sample_batches(batch_size, delivery=delivery, **settings)
        check_delivery(delivery)
        return open_batch_stream(self._for_session(session_id), sample_request(session_id, batch_size, **settings), delivery)

    def describe_session(self, session_id: str) -> SessionInfo:
        transport = self._for_session(session_id)
        return SessionInfo.from_proto(
            transport.call("DescribeSession", pb.DescribeSessionRequest(session_id=session_id)))

    def close_session(self, session_id: str, *, discard_snapshot: bool = False) -> None:
        """Closes a session (a sharded one: its session on every server). A named session's replay
        gets a last snapshot, unless `discard_snapshot` removes its snapshot instead."""
        sharded = self._sharded.pop(session_id, None)
        if sharded is not None:
            sharded.close(discard_snapshot=discard_snapshot)
            return
        self._for_session(session_id).close_session(session_id, discard_snapshot=discard_snapshot)

    def list_sessions(self) -> "list[SessionSummary]":
        """Every open session the caller may see: its own, or every principal's for an admin or a
        monitor token (on a server without tokens every caller is the admin `local`, so that is every
        session); with several servers, every server's in the order of the servers; oldest first:
        what each holds and how long it has been idle. The
        server closes a session idle for longer than its `limits.session_idle_timeout_s`
        (`SessionSummary.idle_timeout_seconds`)."""
        sessions = []
        for transport in self._transports:
            response = transport.call("ListSessions", pb.ListSessionsRequest())
            sessions += [SessionSummary.from_proto(s, response.idle_timeout_seconds, transport.address)
                         for s in response.sessions]
        return sessions

    def close(self) -> None:
        for transport in self._transports:
            transport.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
