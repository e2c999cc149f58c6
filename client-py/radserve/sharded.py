"""One session spread over several radserve servers: a gymnasium VectorEnv and its batch streams.

`Client([...]).make_vec(env_id, num_envs, seed)` gives each server a contiguous share of the envs
(sizes as even as they can be, the first servers taking one more) as a session of its own, seeded so
that env i is still seeded `seed + i`: a sharded session steps exactly the episodes a single-server
session of the same seed steps, whatever the number of servers.

Server loss. gymnasium's vector envs have a fixed `num_envs`, so a lost server's envs keep their
rows. With `on_server_loss="raise"` (the default) the step raises `UnavailableError` naming the
server (`error.server`). With `"continue"` the step that finds the server gone ends its envs'
episodes as truncated (SameStep: the last observation in `final_obs`) and warns; until the server is
back those rows are placeholders (last observation, reward 0, no flags) marked in
`infos["radserve_inactive"]` and `envs.active`, which learners skip when they record transitions.
The lost server is tried again with exponential backoff (`Client(reconnect_backoff=...)`); when it
answers, a new session is created there with the same seeds, and its first observations appear in
that step's rows (still marked inactive: that row's transition is not a real one); the next step is
a normal one. Batches are then drawn from the remaining servers until the new session's replay holds
a batch's share. A learner whose servers act (`start_acting`) makes no step: `set_policy` tries the
lost servers instead, and starts a returned one's actor with the others' settings.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
import uuid
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ._proto import radserve_pb2 as pb
from ._transport import Transport
from .actors import ActingMixin
from .batches import (DEFAULT_IMPORTANCE_SAMPLING_EXPONENT, METADATA_FIELDS, Batch, PriorityUpdate, SamplingMixin,
                      _priority_arrays, importance_weights, make_batch, open_batch_stream, send_priorities)
from .infos import merge_infos
from .errors import InvalidArgumentError, NotFoundError, RadServeError, UnavailableError
from .types import SessionInfo
from .vector import RemoteVectorEnv, check_reset_mask, check_seeds, open_vector_env

SERVER_LOSS = ("raise", "continue")
# A server is lost when it cannot be reached, or when it no longer knows the session (it restarted).
_LOSS = (UnavailableError, NotFoundError)


def apportion(total: int, weights: "list[int]") -> "list[int]":
    """`total` split in proportion to `weights` by largest remainders (ties to the first): the
    shares of envs over servers and of a batch over the servers' replays."""
    weight_sum = sum(weights)
    exact = [total * w / weight_sum for w in weights]
    shares = [int(math.floor(x)) for x in exact]
    order = sorted(range(len(weights)), key=lambda i: (-(exact[i] - shares[i]), i))
    for i in order[: total - sum(shares)]:
        shares[i] += 1
    return shares


@dataclass
class Shard:
    """One server's part of a sharded session."""

    server: int  # index in Client.addresses
    transport: Transport
    start: int  # the first env (global index) this server holds
    size: int
    request: "pb.CreateSessionRequest"
    env: "RemoteVectorEnv | None" = None
    # Loss and reconnection.
    lost: "str | None" = None  # why, while lost
    retry_at: float = 0.0
    backoff: float = 0.0
    # Bumped at every loss and reconnection: batch streams re-plan when it changes.
    generation: int = 0
    last_obs: Any = None
    pending: bool = False
    stats: dict = field(default_factory=dict)

    @property
    def rows(self) -> slice:
        return slice(self.start, self.start + self.size)


class ShardedVectorEnv(ActingMixin, SamplingMixin, VectorEnv):
    """`num_envs` environments spread over several radserve servers, stepped concurrently (one
    outstanding step per server) and returned as one gymnasium VectorEnv in env order.

    Everything `RemoteVectorEnv` does (autoreset modes, seeds, reset masks, infos, deliveries)
    applies per server; the arrays and info dicts are those of one session. `shards` says which
    server holds which envs; `sample_batches` draws from every server's replay. Calls that go to
    every server (`describe`, `set_policy`, `start_acting`, `stop_acting`, `acting`) return a list
    in shard order, None for a server lost now, as a plain env's return a list of one. See the
    module's documentation for what happens when a server is lost.
    """

    def __init__(self, transports: "list[Transport]", request: "pb.CreateSessionRequest", *, stream: bool = False,
                 delivery: str = "grpc", autoreset_mode: "AutoresetMode | str | None" = None,
                 channels_last: bool = False, on_server_loss: str = "raise",
                 reconnect_backoff: "tuple[float, float]" = (1.0, 30.0)):
        if on_server_loss not in SERVER_LOSS:
            raise InvalidArgumentError(f"on_server_loss must be one of {SERVER_LOSS}, got {on_server_loss!r}")
        self._settings = dict(stream=stream, delivery=delivery, autoreset_mode=autoreset_mode,
                              channels_last=channels_last)
        self.on_server_loss = on_server_loss
        # Shards reconnected in this call (their rows are placeholders once more), and the losses
        # step_async found (None while no step is outstanding).
        self._returned_rows: "list[Shard]" = []
        self._pending_losses: "list | None" = None
        self._backoff_first, self._backoff_max = reconnect_backoff
        self.num_envs = request.num_envs
        if self.num_envs < 1:
            raise InvalidArgumentError(f"num_envs must be at least 1, got {self.num_envs}")
        transports = list(transports)
        self.num_servers = len(transports)
        sizes = apportion(self.num_envs, [1] * len(transports))
        capacity = request.replay.capacity if request.HasField("replay") else 0
        self.shards: "list[Shard]" = []
        start = 0
        for server, (transport, size) in enumerate(zip(transports, sizes)):
            if size == 0:
                continue
            shard_request = copy.deepcopy(request)
            shard_request.num_envs = size
            # Env i of the whole session is seeded seed + i wherever it lives.
            shard_request.seed = request.seed + start
            if capacity:
                shard_request.replay.capacity = max(1, math.ceil(capacity * size / self.num_envs))
            self.shards.append(Shard(server, transport, start, size, shard_request))
            start += size
        try:
            for shard in self.shards:
                shard.env = open_vector_env(shard.transport, shard.request, **self._settings)
        except BaseException:
            self.close()
            raise
        first = self.shards[0].env
        for shard in self.shards[1:]:
            if shard.env.single_observation_space != first.single_observation_space or \
                    shard.env.single_action_space != first.single_action_space:
                self.close()
                raise RadServeError(f"servers {self.shards[0].transport.address} and {shard.transport.address} give "
                                    f"{request.env_id} different spaces: run the same radserve version everywhere")
        self.autoreset_mode = first.autoreset_mode
        self.metadata = {"autoreset_mode": self.autoreset_mode}
        self.single_observation_space = first.single_observation_space
        self.single_action_space = first.single_action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.session_id = f"sharded-{uuid.uuid4().hex}"
        # The session as one: the first shard's settings, the whole session's size and seed.
        self.info = dataclasses.replace(first.info, session_id=self.session_id, num_envs=self.num_envs,
                                        seed=request.seed)
        self.closed = False

    # --- what the sharded session is made of -------------------------------------------------

    @property
    def servers(self) -> "list[str]":
        """The address of each shard's server, in shard (env) order."""
        return [shard.transport.address for shard in self.shards]

    @property
    def _acting_servers(self) -> int:
        return len(self.shards)

    def _acting_sessions(self):
        """Each served shard's (transport, session id, envs, position): a policy goes to every server."""
        self._check_open()
        return [(shard.transport, shard.env.session_id, shard.size, position) for position, shard in enumerate(self.shards)
                if not shard.lost and shard.env is not None]

    def _acting_returned(self) -> list:
        """With on_server_loss="continue", a learner whose servers act makes no step, where lost
        servers are otherwise tried again: set_policy tries them (see `_reconnect_due`)."""
        if self.on_server_loss != "continue":
            return []
        self._check_open()
        returned = self._reconnect_due()
        return [(shard.transport, shard.env.session_id, shard.size, self.shards.index(shard)) for shard in returned]

    @property
    def session_ids(self) -> "list[str | None]":
        """Each shard's session id on its server (None while lost)."""
        return [None if shard.lost or shard.env is None else shard.env.session_id for shard in self.shards]

    @property
    def active(self) -> np.ndarray:
        """Which envs are served now (False: their server is lost)."""
        active = np.ones(self.num_envs, dtype=bool)
        for shard in self.shards:
            if shard.lost:
                active[shard.rows] = False
        return active

    @property
    def delivery(self) -> str:
        """"shared_memory" or "grpc" when every live shard uses it, else "mixed"."""
        kinds = {shard.env.delivery for shard in self.shards if shard.env is not None and not shard.lost}
        return kinds.pop() if len(kinds) == 1 else "mixed"

    def describe(self) -> "list[SessionInfo | None]":
        """Each shard's session as its server sees it, in shard (env) order; None for a lost one."""
        return [None if shard.env is None or shard.lost else shard.env.describe()[0] for shard in self.shards]

    def _open_batches(self, request: "pb.SampleBatchesRequest", delivery: str) -> "ShardedBatchStream":
        self._check_open()
        return ShardedBatchStream(self, request, delivery)

    # --- stepping -----------------------------------------------------------------------------

    def reset(self, *, seed: "int | list[int | None] | None" = None, options: "dict[str, Any] | None" = None):
        """As `RemoteVectorEnv.reset`: `seed` an int (env i gets seed + i), one per env, or None;
        `options["reset_mask"]` resets only the marked envs."""
        self._check_open()
        options = dict(options or {})
        # The plain env's checks, before any server is asked: the same refusals, sharded or not.
        mask = check_reset_mask(options.pop("reset_mask", None), self.num_envs)
        check_seeds(seed, self.num_envs)
        returned = self._reconnect_due()
        parts, lost = [], []
        for shard in self.shards:
            shard_mask = None if mask is None else mask[shard.rows]
            if shard.lost or (shard_mask is not None and not shard_mask.any()):
                continue
            if shard in returned and (shard_mask is None or shard_mask.all()):
                self._returned_rows.remove(shard)  # this reset makes its rows real ones
            if seed is None or isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
                shard_seed = None if seed is None else int(seed) + shard.start
            else:
                shard_seed = list(seed[shard.rows])
            try:
                obs, info = shard.env.reset(seed=shard_seed, options=None if shard_mask is None else
                                            {**options, "reset_mask": shard_mask})
            except _LOSS as error:
                lost.append(self._lose(shard, error))
                continue
            shard.last_obs = obs
            parts.append((shard.start, shard.size, info))
        obs = self._gather()
        infos = merge_infos(parts, self.num_envs)
        self._mark_inactive(infos, lost)
        return obs, infos

    def step(self, actions):
        self.step_async(actions)
        return self.step_wait()

    def step_async(self, actions) -> None:
        """Sends each server its envs' actions and returns; `step_wait()` gathers the results."""
        self._check_open()
        actions = np.asarray(actions)
        if actions.ndim == 0 or actions.shape[0] != self.num_envs:
            raise InvalidArgumentError(f"actions must have one row per env ({self.num_envs}), got shape "
                                       f"{list(actions.shape)}")
        if self._pending_losses is not None:
            raise RuntimeError("step_async() while a step_async() awaits its step_wait()")
        returned = self._reconnect_due()  # their rows hold their new sessions' first observations
        self._pending_losses = []
        for shard in self.shards:
            if shard.lost or shard in returned:
                continue
            try:
                shard.env.step_async(actions[shard.rows])
                shard.pending = True
            except _LOSS as error:
                self._pending_losses.append(self._lose(shard, error))
            except BaseException:  # the caller's (a wrong action): no step stays outstanding anywhere
                self._settle()
                raise

    def step_wait(self):
        """What `step(actions)` returns, once every server has answered."""
        if self._pending_losses is None:
            raise RuntimeError("step_wait() without a step_async() before it")
        n = self.num_envs
        rewards = np.zeros(n, dtype=np.float64)
        terminated = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        parts = []
        failure: "Exception | None" = None
        lost, self._pending_losses = self._pending_losses, None
        for shard in self.shards:
            if not shard.pending:
                continue
            shard.pending = False
            try:
                obs, reward, term, trunc, info = shard.env.step_wait()
            except _LOSS as error:
                lost.append(self._lose(shard, error, raise_later=True))
                continue
            except RadServeError as error:  # the caller's or the simulator's: raised once all answered
                failure = failure or error
                continue
            shard.last_obs = obs
            rewards[shard.rows], terminated[shard.rows], truncated[shard.rows] = reward, term, trunc
            parts.append((shard.start, shard.size, info))
        if failure is not None:
            raise failure
        if self.on_server_loss == "raise" and lost:
            raise lost[0]
        obs = self._gather()
        # The lost envs' episodes end as truncated (SameStep: their last observation as final_obs).
        for shard in lost:
            truncated[shard.rows] = True
            if self.autoreset_mode == AutoresetMode.SAME_STEP:
                final = np.full(shard.size, None, dtype=object)
                for row in range(shard.size):
                    final[row] = shard.last_obs[row]
                parts.append((shard.start, shard.size, {
                    "final_obs": final, "_final_obs": np.ones(shard.size, dtype=bool),
                    "final_info": {}, "_final_info": np.ones(shard.size, dtype=bool)}))
        infos = merge_infos(parts, n)
        self._mark_inactive(infos, lost)
        return obs, rewards, terminated, truncated, infos

    def _settle(self) -> None:
        """Reads and drops the answers of the steps already sent."""
        for shard in self.shards:
            if shard.pending:
                shard.pending = False
                try:
                    shard.last_obs = shard.env.step_wait()[0]
                except RadServeError:
                    pass
        self._pending_losses = None

    def _gather(self) -> np.ndarray:
        return np.concatenate([shard.last_obs for shard in self.shards], axis=0)

    def _mark_inactive(self, infos: dict, lost: "list[Shard]") -> None:
        inactive = ~self.active
        for shard in self._returned_rows:
            inactive[shard.rows] = True
        self._returned_rows = []
        if inactive.any() or lost:
            infos["radserve_inactive"] = inactive
            infos["_radserve_inactive"] = inactive.copy()
        if lost:
            lost_mask = np.zeros(self.num_envs, dtype=bool)
            for shard in lost:
                lost_mask[shard.rows] = True
            infos["radserve_server_lost"] = lost_mask
            infos["_radserve_server_lost"] = lost_mask.copy()

    def _lose(self, shard: Shard, error: RadServeError, raise_later: bool = False) -> "Shard | Exception":
        """Marks a shard lost (continue) or returns the error that names it (raise)."""
        if self.on_server_loss == "raise":
            if isinstance(error, UnavailableError):
                return error
            return UnavailableError(f"server {shard.transport.address} lost session {shard.env.session_id}: "
                                    f"{error.details}", error.code, server=shard.transport.address)
        shard.lost = str(error)
        shard.generation += 1
        shard.backoff = self._backoff_first
        shard.retry_at = time.monotonic() + shard.backoff
        if shard.env is not None:
            shard.env.close(timeout=1.0)
        warnings.warn(f"radserve: server {shard.transport.address} lost ({error}); envs {shard.start}.."
                      f"{shard.start + shard.size - 1} end their episodes as truncated and are inactive until it "
                      f"returns", RuntimeWarning, stacklevel=3)
        return shard

    def _reconnect_due(self) -> "list[Shard]":
        """Tries the lost servers whose backoff has passed; those that answer get a new session
        (reset with the original seeds), whose first observations fill their rows."""
        returned = []
        now = time.monotonic()
        for shard in self.shards:
            if not shard.lost or now < shard.retry_at:
                continue
            try:
                if not _ready(shard.transport, 0.25):
                    raise UnavailableError("not reachable")
                env = open_vector_env(shard.transport, shard.request, **self._settings)
                obs, _ = env.reset(seed=shard.request.seed)
            except RadServeError:
                shard.backoff = min(self._backoff_max, shard.backoff * 2)
                shard.retry_at = time.monotonic() + shard.backoff
                continue
            shard.env, shard.last_obs, shard.lost = env, obs, None
            shard.generation += 1
            warnings.warn(f"radserve: server {shard.transport.address} is back: a new session holds envs "
                          f"{shard.start}..{shard.start + shard.size - 1}", RuntimeWarning, stacklevel=3)
            returned.append(shard)
        self._returned_rows = list(returned)
        return returned

    def _check_open(self) -> None:
        if self.closed:
            raise RuntimeError("the sharded session is closed")

    def close(self, *, discard_snapshot: bool = False, **kwargs) -> None:
        if getattr(self, "closed", False):
            return
        self.closed = True
        for shard in self.shards:
            if shard.env is not None:
                shard.env.close(timeout=2.0, discard_snapshot=discard_snapshot)


def _ready(transport: Transport, timeout: float) -> bool:
    import grpc

    try:
        grpc.channel_ready_future(transport.raw_channel).result(timeout=timeout)
        return True
    except grpc.FutureTimeoutError:
        return False


class ShardedBatchStream:
    """Batches of `batch_size` drawn from every server of a sharded session.

    Each server samples and augments its share of the batch from its own replay (shares in
    proportion to its envs, so to its share of the transitions); the client concatenates the parts
    in server order. `Batch.server` says which server (index in `Client.addresses`) each transition
    came from, `env_index` is the env's index in the whole session, and `shares` the current split.
    A lost server's share moves to the others (with `on_server_loss="continue"`); a returned server
    takes its share again once its new session's replay holds it.
    """

    def __init__(self, envs: ShardedVectorEnv, request: "pb.SampleBatchesRequest", delivery: str):
        self._envs = envs
        self._request = request
        self._delivery = delivery
        self._streams: "list[tuple[Shard, int, Any]]" = []
        self._generations: "tuple[int, ...]" = ()
        # Live shards left out of the plan until their (new) replay holds their share.
        self._waiting: "list[Shard]" = []
        self._plans = 0
        self._next_check = 0.0
        # Batches handed out (each batch's index), and per server the session generation the
        # stream last drew from and the first batch index drawn from it: keys of earlier batches
        # name transitions of a session the server no longer has.
        self._count = 0
        self._generation_of: "dict[int, int]" = {}
        self._since: "dict[int, int]" = {}
        self._open()

    @property
    def shares(self) -> "dict[str, int]":
        """Server address -> transitions of each batch drawn there, now."""
        return {shard.transport.address: share for shard, share, _ in self._streams}

    def _open(self) -> None:
        """Opens one stream per live shard with its share of the batch."""
        self._close_streams()
        request, envs = self._request, self._envs
        candidates = [shard for shard in envs.shards if not shard.lost and shard.env is not None]
        if not candidates:
            raise UnavailableError(f"every server of the sharded session is lost: {envs.servers}")
        shares = apportion(request.batch_size, [shard.size for shard in candidates])
        first_plan = self._plans == 0
        self._plans += 1
        planned, self._waiting = [], []
        for shard, share in zip(candidates, shares):
            if share == 0:
                continue
            if not first_plan and shard.generation > 0 and not self._holds(shard, share):
                self._waiting.append(shard)  # a returned server whose new replay cannot fill its share yet
                continue
            planned.append((shard, share))
        if not planned:
            raise UnavailableError(f"no server of the sharded session can fill a batch: {envs.servers}")
        if len(planned) != len(candidates):
            shares = apportion(request.batch_size, [shard.size for shard, _ in planned])
            planned = [(shard, share) for (shard, _), share in zip(planned, shares)]
        total_envs = envs.num_envs
        for shard, share in planned:
            shard_request = copy.deepcopy(request)
            shard_request.session_id = shard.env.session_id
            shard_request.batch_size = share
            # Different draws on every server (and after every re-plan), reproducible from `seed`.
            shard_request.seed = request.seed + shard.server + envs.num_servers * (self._plans - 1)
            if request.HasField("min_size"):
                shard_request.min_size = max(share, math.ceil(request.min_size * shard.size / total_envs))
            try:
                stream = open_batch_stream(shard.transport, shard_request, self._delivery)
            except _LOSS as error:
                self._lost(shard, error)
                return self._open()
            self._streams.append((shard, share, stream))
        self._generations = tuple(shard.generation for shard in envs.shards)
        for shard in envs.shards:
            if self._generation_of.setdefault(shard.server, shard.generation) != shard.generation:
                self._generation_of[shard.server] = shard.generation
                self._since[shard.server] = self._count

    def _holds(self, shard: Shard, share: int) -> bool:
        try:
            info = shard.env.describe()[0]
        except RadServeError:
            return False
        return info.replay is not None and info.replay.size >= share

    def _lost(self, shard: Shard, error: RadServeError) -> None:
        result = self._envs._lose(shard, error) if not shard.lost else shard
        if isinstance(result, Exception):
            self._close_streams()
            raise result

    def __iter__(self) -> "ShardedBatchStream":
        return self

    def __next__(self) -> Batch:
        envs = self._envs
        now = time.monotonic()
        changed = tuple(shard.generation for shard in envs.shards) != self._generations
        if changed or (self._waiting and now >= self._next_check):
            # At most once a second, a waiting server's replay is asked whether it can take its share.
            self._next_check = now + 1.0
            share = max(1, self._request.batch_size // len(envs.shards))
            if changed or any(not shard.lost and self._holds(shard, share) for shard in self._waiting):
                self._open()
        parts = []
        for shard, share, stream in self._streams:
            try:
                batch = next(stream)
            except StopIteration:  # a rollout's epochs are over on one server: the stream ends
                self._close_streams()
                raise
            except _LOSS as error:
                self._lost(shard, error)
                self._open()
                return next(self)
            parts.append((shard, batch))
        batch = _concatenate(parts)
        batch.index, self._count = self._count, self._count + 1
        if batch.probability is not None and len(parts) > 1:
            # Server s draws n_s of the batch's B transitions, each with its own probability p_s(i):
            # a transition's probability per draw of the whole batch is n_s * p_s(i) / B, among the
            # transitions every server could draw.
            share = np.concatenate([np.full(len(part), len(part) / len(batch)) for _, part in parts])
            batch.probability = batch.probability * share
            batch.table_size = np.full(len(batch), sum(int(part.table_size[0]) for _, part in parts), dtype=np.int64)
            request = self._request
            beta = (request.importance_sampling_exponent if request.HasField("importance_sampling_exponent")
                    else DEFAULT_IMPORTANCE_SAMPLING_EXPONENT)
            batch.weight = importance_weights(batch.probability, batch.table_size, beta)
        return batch

    def update_priorities(self, batch: Batch, priorities: Any) -> PriorityUpdate:
        """Replace the priorities of `batch`'s transitions (`sampler="prioritized"`), each on the
        server it came from (`Batch.server`); keys of a lost server count as missing, and so do keys
        drawn from a server's earlier session (it was lost and came back with a new one)."""
        keys, values = _priority_arrays(batch, priorities)
        total = PriorityUpdate(updated=0, missing=0)
        for shard in self._envs.shards:
            rows = np.asarray(batch.server) == shard.server
            if not rows.any():
                continue
            stale = batch.index < self._since.get(shard.server, 0)  # drawn from an earlier session
            if stale or shard.lost or shard.env is None:
                total += PriorityUpdate(updated=0, missing=int(rows.sum()))
                continue
            try:
                total += send_priorities(shard.transport, shard.env.session_id, keys[rows], values[rows])
            except _LOSS as error:
                self._lost(shard, error)
                total += PriorityUpdate(updated=0, missing=int(rows.sum()))
        return total

    def _close_streams(self) -> None:
        for _, _, stream in self._streams:
            stream.close()
        self._streams = []

    def close(self) -> None:
        self._close_streams()

    def __enter__(self) -> "ShardedBatchStream":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def _concatenate(parts: "list[tuple[Shard, Batch]]") -> Batch:
    arrays = {}
    batches = [batch for _, batch in parts]
    for name in METADATA_FIELDS:
        values = [getattr(batch, name) for batch in batches]
        if any(value is None for value in values):
            continue
        arrays[name] = np.concatenate([np.asarray(value) for value in values], axis=0)
    for name in batches[0].views:
        arrays[name] = np.concatenate([np.asarray(batch.views[name]) for batch in batches], axis=0)
    arrays["env_index"] = np.concatenate([np.asarray(batch.env_index) + shard.start for shard, batch in parts])
    arrays["server"] = np.concatenate([np.full(len(batch), shard.server, dtype=np.int32) for shard, batch in parts])
    return make_batch(batches[0].index, arrays, list(batches[0].views))
