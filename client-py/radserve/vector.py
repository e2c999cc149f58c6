"""A radserve session as a gymnasium VectorEnv."""

import queue
from typing import Any, NamedTuple

import grpc
import numpy as np
from gymnasium.spaces import Box
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from . import _convert
from ._shared_stepping import Answer, SharedStepping
from .actors import ActingMixin
from .batches import SamplingMixin, open_batch_stream
from ._proto import radserve_pb2 as pb
from ._transport import Transport, check_delivery
from .errors import FailedPreconditionError, InvalidArgumentError, RadServeError
from .infos import add_flat, env_infos, episode_infos, is_flat, vector_infos
from .types import SessionInfo


class _Step(NamedTuple):
    """A step as the server returns it (same-step autoreset), before this env's mode applies."""

    obs: Any
    rewards: Any
    terminated: Any
    truncated: Any
    ended: Any  # env indices whose episode ended, in the order of the rows below
    final_rows: Any
    returns: Any
    lengths: Any
    errors: "dict[int, str]"
    # The envs' infos from the step, and from the resets the server made in it (pb.InfoColumn)
    step_infos: Any
    reset_infos: Any


def _bools(mask) -> "list[bool]":
    return [] if mask is None else [bool(value) for value in mask]


def check_reset_mask(mask, num_envs: int) -> "np.ndarray | None":
    """`reset(options={"reset_mask": mask})`'s mask, checked: None, or a numpy bool array of `num_envs`
    marking at least one env (gymnasium's own rule), for a plain and a sharded env alike."""
    if mask is None:
        return None
    if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ or mask.shape != (num_envs,):
        raise InvalidArgumentError(
            f"options['reset_mask'] must be a numpy bool array of shape ({num_envs},), got {mask!r}")
    if not mask.any():
        raise InvalidArgumentError("options['reset_mask'] must mark at least one env")
    return mask


def check_seeds(seed, num_envs: int) -> "tuple[int | None, list[int] | None]":
    """`reset(seed=...)` as (a session seed, or one seed per env), checked: an int (env i gets seed + i),
    a list of one int per env, or None (each env's random stream goes on)."""
    if seed is None:
        return None, None
    if isinstance(seed, (list, tuple, np.ndarray)):
        seeds = list(seed)
        if len(seeds) != num_envs:
            raise InvalidArgumentError(f"reset got {len(seeds)} seeds for {num_envs} envs")
        if all(entry is None for entry in seeds):
            return None, None
        if any(entry is None for entry in seeds):
            raise InvalidArgumentError(
                f"a list of seeds is all ints or all None (to leave one env unseeded, reset the others with "
                f"options={{'reset_mask': ...}}), got {seeds}")
        for entry in seeds:
            _check_seed(entry)
        seeds = [int(entry) for entry in seeds]
        if all(entry == seeds[0] + i for i, entry in enumerate(seeds)):
            return seeds[0], None
        return None, seeds
    _check_seed(seed)
    return int(seed), None


def _check_seed(seed) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise InvalidArgumentError(f"seed must be an int, a list of ints or None, got {seed!r}")
    if not 0 <= int(seed) < 1 << 64:
        raise InvalidArgumentError(f"seed must be a non-negative integer, got {seed}")


def resolve_autoreset_mode(mode: "AutoresetMode | str | None", is_async: bool = False) -> AutoresetMode:
    """`make_vec`'s `autoreset_mode` as gymnasium's enum. None (the default) is gymnasium's own default,
    NEXT_STEP, which its vector observation wrappers require; a session in EnvPool's asynchronous mode
    resets an env in the step that ends its episode, so there None is SAME_STEP, its only mode."""
    if mode is None:
        return AutoresetMode.SAME_STEP if is_async else AutoresetMode.NEXT_STEP
    try:
        return AutoresetMode(mode)
    except ValueError:
        raise InvalidArgumentError(
            f"autoreset_mode must be a gymnasium.vector.AutoresetMode or one of "
            f"{[value.value for value in AutoresetMode]}, got {mode!r}") from None


def _ended_episodes(step: "pb.StepResponse"):
    """A step's (or recv's) ended episodes: their env ids, last observations, returns, lengths and the
    simulators' messages by env."""
    episodes = step.episodes
    return (np.array([episode.env_index for episode in episodes], dtype=np.int64),
            _convert.to_numpy(step.final_obs) if episodes else None,
            [episode.episode_return for episode in episodes], [episode.episode_length for episode in episodes],
            {episode.env_index: episode.error for episode in episodes if episode.error})


class RemoteVectorEnv(ActingMixin, SamplingMixin, VectorEnv):
    """`num_envs` environments living in a radserve server, stepped together.

    Autoreset follows gymnasium's `AutoresetMode` (`metadata["autoreset_mode"]`), chosen at
    `make_vec(autoreset_mode=...)`, and behaves as gymnasium's SyncVectorEnv does in that mode:

    - NEXT_STEP (the default, as gymnasium's): the step that ends an episode returns its last
      observation; the next step ignores that env's action and returns the first observation of its
      next episode, reward 0, no flags.
    - SAME_STEP (the default of a session in EnvPool's asynchronous mode, its only mode; radserve's
      learners choose it): when an episode ends, the returned observation of that env already starts
      the next episode; `infos["final_obs"][i]` holds the last observation of the ended one
      (`infos["_final_obs"]` the mask) and `infos["final_info"]` the ended episodes' infos.
    - DISABLED: an ended env must be reset with `reset(options={"reset_mask": mask})` before it is
      stepped again.

    `reset(options={"reset_mask": mask})` resets only the marked envs in every mode; `seed` is an
    int (env i gets seed + i), a list of one seed per env, or None (every env's random stream goes on).

    radserve's own per-episode figures are under names gymnasium's wrappers do not use:
    `infos["radserve_episode"]` has the return `r` and length `l` of ended episodes (mask
    `infos["_radserve_episode"]`), and `infos["radserve_error"][i]` the simulator's message when it
    raised or its worker died (mask `infos["_radserve_error"]`).

    Delivery: "grpc" steps through unary calls (or one bidirectional stream with `stream=True`);
    "shared_memory" steps through memory shared with a server on the same host (shared stepping,
    rpc ShareActing: the actions and results never become messages, a 16-byte request per step goes
    over a Unix socket);
    "auto" uses shared memory when it can be mapped and gRPC otherwise. `delivery` says which is used.

    Observations are this env's own writable arrays (gymnasium's `copy=True`), whichever delivery.
    """

    def __init__(self, transport: Transport, info, *, stream: bool = False, delivery: str = "grpc",
                 autoreset_mode: "AutoresetMode | str | None" = None, channels_last: bool = False):
        check_delivery(delivery)
        # EnvPool's asynchronous mode (option batch_size below num_envs): async_reset, send, recv.
        batch_size = int(info.options.get("batch_size", 0) or 0)
        self.num_envs = info.num_envs
        self.batch_size = batch_size if 0 < batch_size < self.num_envs else self.num_envs
        self.is_async = self.batch_size < self.num_envs
        self.autoreset_mode = resolve_autoreset_mode(autoreset_mode, self.is_async)
        self.metadata = {"autoreset_mode": self.autoreset_mode}
        self._transport = transport
        self.info = info
        self.session_id = info.session_id
        self.single_observation_space = info.observation_space
        # Image observations as [H, W, C] (the transpose is made here, on the way out).
        self._channels_last = bool(channels_last)
        if self._channels_last:
            space = info.observation_space
            if len(space.shape) != 3:
                raise InvalidArgumentError(f"channels_last needs image observations [C, H, W]; {info.env_id} observes {space}")
            self.single_observation_space = Box(
                np.moveaxis(space.low, 0, -1), np.moveaxis(space.high, 0, -1), dtype=space.dtype)
        self.single_action_space = info.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._action_dtype = np.dtype(np.int64) if info.action_space.shape == () else info.action_space.dtype
        # Whether a step without ended episodes or infos is returned as the server wrote it (_shared_result).
        self._plain_mode = self.autoreset_mode == AutoresetMode.SAME_STEP and not self._channels_last
        if self.is_async and self.autoreset_mode != AutoresetMode.SAME_STEP:
            raise InvalidArgumentError(
                f"a session in EnvPool's asynchronous mode (batch_size {self.batch_size} below num_envs "
                f"{self.num_envs}) resets an env in the step that ends its episode: autoreset_mode must be "
                f"SameStep, got {self.autoreset_mode.value}")
        self._requests: "queue.Queue | None" = None
        self._responses = None
        self._pending = None  # the step sent by step_async, until step_wait takes its reply
        self._shared: "SharedStepping | None" = None
        # Envs whose episode ended in the last step, already reset on the server (which resets in
        # the ending step): NEXT_STEP's next step skips them, DISABLED waits for their reset.
        self._ended = np.zeros(self.num_envs, dtype=bool)
        # What the server last returned (its current observation of every env), and what this env
        # last returned (they differ in the rows of ended envs under NEXT_STEP and DISABLED).
        self._server_obs = None
        self._last_obs = None
        # Reset infos of envs the server reset in the step that ended their episode, until this env
        # returns them (NEXT_STEP: in the next step; DISABLED: in their reset).
        self._held_reset_infos: "dict[int, dict | None]" = {}

        def shared() -> SharedStepping:
            channel = transport.call("ShareActing", pb.ShareActingRequest(session_id=self.session_id))
            action_shape = () if info.action_space.shape == () else info.action_space.shape
            return SharedStepping(channel, self.num_envs, info.observation_space, self._action_dtype, action_shape,
                                explain_loss=self._session_error)

        self._shared = transport.negotiate(delivery, shared, lambda: None)
        self.delivery = "grpc" if self._shared is None else "shared_memory"
        if stream and self._shared is None:
            self._requests = queue.Queue()
            self._responses = transport.stub.Act(iter(self._requests.get, None))
        self.closed = False

    def _session_error(self) -> "Exception | None":
        """What the server says of this session now (NotFoundError once it is closed), or None."""
        try:
            self._transport.call("DescribeSession", pb.DescribeSessionRequest(session_id=self.session_id))
        except RadServeError as error:
            return error
        return None

    def _act(self, request: "pb.ActRequest", kind: str):
        if self._requests is None:
            method = "Reset" if kind == "reset" else "Step"
            return self._transport.call(method, getattr(request, kind))
        self._requests.put(request)
        try:
            return getattr(next(self._responses), kind)
        except grpc.RpcError as error:
            raise self._transport.error(error) from None

    def reset(self, *, seed: "int | list[int | None] | None" = None, options: "dict[str, Any] | None" = None):
        """Resets every environment, or those `options["reset_mask"]` marks (a bool array of
        `num_envs`, as in gymnasium). `seed`: an int (env i is re-seeded with seed + i), a list of
        one int per env, or None (each env's random stream goes on)."""
        self._check_idle("reset")
        options = dict(options or {})
        mask = check_reset_mask(options.pop("reset_mask", None), self.num_envs)
        seed, env_seeds = check_seeds(seed, self.num_envs)
        requested = np.ones(self.num_envs, dtype=bool) if mask is None else mask
        # Ended envs were reset by the server in the step that ended them: an unseeded reset takes
        # that reset instead of a second one, as gymnasium's env resets once.
        on_server = requested if seed is not None or env_seeds is not None else requested & ~self._ended
        if on_server.any():
            server_mask = None if on_server.all() else on_server
            if self._shared is not None:
                self._shared.send(b"R", seed, mask=server_mask, env_seeds=env_seeds)
                reset_infos = env_infos(self._shared.receive().reset_infos)
                server_obs = self._shared.obs.copy()
            else:
                request = pb.ResetRequest(session_id=self.session_id, seed=seed, mask=_bools(server_mask),
                                          env_seeds=env_seeds or [])
                response = self._act(pb.ActRequest(reset=request), "reset")
                server_obs = _convert.to_numpy(response.obs).copy()
                reset_infos = env_infos(response.reset_infos)
        else:
            server_obs, reset_infos = self._server_obs, {}
        # Each env's reset info, as gymnasium's SyncVectorEnv batches them (env order, `_key` masks).
        infos: dict = {}
        for i in np.flatnonzero(requested):
            held = self._held_reset_infos.pop(i, None)
            infos = self._add_info(infos, (reset_infos.get(i) if on_server[i] else held) or {}, int(i))
        if mask is None or self._last_obs is None:
            obs = server_obs.copy()
        else:
            obs = self._last_obs.copy()
            obs[mask] = server_obs[mask]
        self._ended[requested] = False
        self._server_obs, self._last_obs = server_obs, obs
        return self._present(obs), infos

    def _present(self, obs: np.ndarray) -> np.ndarray:
        """Observations as this env returns them: its own copy, channels last if asked."""
        if self._channels_last:
            return np.ascontiguousarray(np.moveaxis(obs, -3, -1))
        return obs.copy()

    def _skip(self) -> "np.ndarray | None":
        """The envs this step must not step (NEXT_STEP: those that ended in the last step)."""
        if not self._ended.any():
            return None
        if self.autoreset_mode == AutoresetMode.DISABLED:
            raise FailedPreconditionError(
                f"autoreset is disabled and envs {np.flatnonzero(self._ended).tolist()} ended: reset them with "
                f"reset(options={{'reset_mask': mask}}) before stepping")
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            return self._ended.copy()
        return None

    def step(self, actions, env_id=None):
        """gymnasium's step. In EnvPool's asynchronous mode (`is_async`) EnvPool's instead:
        `send(actions, env_id)` then `recv()`, in one round trip."""
        if self.is_async:
            return self._recv(*self._async_actions(actions, env_id))
        if env_id is not None:
            raise InvalidArgumentError(
                "step(actions, env_id) is for sessions in EnvPool's asynchronous mode (batch_size below num_envs); "
                "this one steps every env: step(actions)")
        self._check_idle("step")
        skip = self._skip()
        if self._shared is not None:
            self._write_actions(actions)
            self._shared.send(b"S", mask=skip)
            return self._shared_result(self._shared.receive())
        return self._grpc_result(self._act(pb.ActRequest(step=self._step_request(actions, skip)), "step"))

    # The common step (SameStep, no episode ended, no info, observations as the server lays them out)
    # is returned as the server wrote it, without _finish's bookkeeping: ~20 numpy calls, 5-10% of the
    # steps/s of a 16-env state session through shared memory (docs/performance.md).

    def _shared_result(self, answer: "Answer"):
        shared = self._shared
        if self._plain_mode and not answer.errors and not answer.reset_infos and \
                not (shared.terminated.any() or shared.truncated.any()):
            infos = vector_infos(answer.step_infos, self.num_envs)
            if infos is not None:
                obs = shared.obs.copy()
                self._last_obs = obs
                return obs, shared.reward.copy(), shared.terminated.copy(), shared.truncated.copy(), infos
        return self._finish(self._unpack_shared(answer))

    def _grpc_result(self, response: "pb.StepResponse"):
        if self._plain_mode and not response.episodes and not response.reset_infos:
            infos = vector_infos(response.step_infos, self.num_envs)
            if infos is not None:
                obs = _convert.to_numpy(response.obs).copy()
                self._last_obs = obs
                return (obs, _convert.to_numpy(response.reward), np.array(response.terminated, dtype=bool),
                        np.array(response.truncated, dtype=bool), infos)
        return self._finish(self._unpack(response))

    def step_async(self, actions) -> None:
        """Sends a step and returns at once; `step_wait()` returns what `step(actions)` would have.

        This is EnvPool's send/recv split, for pipelining: a learner holding two sessions sends one's
        step, then works on the other's observations while the server steps the first, so neither
        the workers nor the learner wait for each other. One step may be outstanding per session.
        Errors (a wrong action shape, an unknown session) are raised by `step_wait()`."""
        self._check_idle("step_async")
        skip = self._skip()
        if self._shared is not None:
            self._write_actions(actions)
            self._shared.send(b"S", mask=skip)
            self._pending = self._shared
            return
        request = self._step_request(actions, skip)
        if self._requests is None:
            self._pending = self._transport.future("Step", request)
        else:
            self._requests.put(pb.ActRequest(step=request))
            self._pending = self._responses

    def step_wait(self):
        """The reply to the step sent by `step_async()`."""
        if self._pending is None:
            raise RuntimeError("step_wait() without a step_async() before it")
        pending, self._pending = self._pending, None
        if self._shared is not None:
            return self._shared_result(self._shared.receive())
        try:
            response = pending.result() if self._requests is None else next(pending).step
        except grpc.RpcError as error:
            raise self._transport.error(error) from None
        return self._grpc_result(response)

    # --- EnvPool's asynchronous mode ----------------------------------------------------------------
    # A session created with batch_size below num_envs is stepped as EnvPool's users step theirs
    # (envpool.readthedocs.io, "Asynchronous API"): async_reset() once, then recv() the first
    # batch_size envs whose step is done and send() them their next actions, so the simulators never
    # wait for the slowest env nor for the learner. Episodes reset in the step that ends them, as in
    # the synchronous mode (infos["final_obs"]). engine="envpool": EnvPool's own asynchronous mode, any
    # batch_size; engine="native": groups of batch_size envs (num_envs a multiple of it), each stepped
    # whole in its worker process, recv returning the first group done and send taking whole groups.

    def async_reset(self, seed: "int | None" = None) -> None:
        """Starts every env's reset (env i re-seeded with seed + i when `seed` is given); their first
        observations come back through recv(), batch_size at a time (reward 0, no flags)."""
        self._check_async("async_reset")
        seed = None if seed is None else check_seeds(seed, self.num_envs)[0]
        if self._shared is not None:
            self._shared.send(b"A", seed)
            self._shared.receive()
        else:
            self._transport.call("AsyncReset", pb.AsyncResetRequest(session_id=self.session_id, seed=seed))

    def send(self, actions, env_id=None) -> None:
        """Starts the next step of the envs `env_id` names (ints, one per row of `actions`; None: envs
        0 to len(actions) - 1) without waiting for it. Each must be an env recv() returned last."""
        rows, ids = self._async_actions(actions, env_id)
        if self._shared is not None:
            self._shared.send(b"E", mask=self._sent_mask(rows, ids))
            self._shared.receive()
        else:
            self._transport.call("Send", pb.SendRequest(session_id=self.session_id, actions=_convert.to_tensor(rows),
                                                        env_ids=ids.tolist()))

    def recv(self):
        """Waits for the next batch_size envs whose step (or reset) is done: (obs, rewards, terminated,
        truncated, infos), row k for env infos["env_id"][k] (ascending). infos also holds, for the rows
        whose episode ended, "final_obs" (with "_final_obs"), "radserve_episode" and "radserve_error"."""
        return self._recv(None, None)

    def _check_async(self, what: str) -> None:
        if not self.is_async:
            raise FailedPreconditionError(
                f"{what}() is for sessions in EnvPool's asynchronous mode: create one with batch_size below "
                f"num_envs; this one ({self.num_envs} envs) steps with reset()/step()")

    def _async_actions(self, actions, env_id) -> "tuple[np.ndarray, np.ndarray]":
        """`actions` in the action dtype and the env ids they go to, checked for shape here (values and
        ids are the server's to check)."""
        self._check_async("send")
        rows = self._in_action_dtype(actions)
        if env_id is None:
            ids = np.arange(len(rows), dtype=np.int64)
        else:
            ids = np.asarray(env_id).reshape(-1)
            if not np.issubdtype(ids.dtype, np.integer):
                raise InvalidArgumentError(f"env_id must be integers, got {ids.dtype}")
        shape = (len(ids),) + tuple(self.single_action_space.shape)
        if rows.shape != shape or not 0 < len(ids) <= self.num_envs:
            raise InvalidArgumentError(
                f"actions must be of shape {list(shape)}: one row per env_id ({len(ids)}), each "
                f"{self.single_action_space}; got {rows.dtype} of shape {list(rows.shape)}")
        if ids.min() < 0 or ids.max() >= self.num_envs:
            raise InvalidArgumentError(f"env_id must be in [0, {self.num_envs}), got {ids.tolist()}")
        return rows, ids.astype(np.int64)

    def _sent_mask(self, rows: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Writes `rows` at the envs' rows of the shared actions; the mask of those envs."""
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[ids] = True
        if mask.sum() != len(ids):
            raise InvalidArgumentError(f"env_id names an env twice: {ids.tolist()}")
        self._shared.actions[ids] = rows
        return mask

    def _recv(self, rows, ids):
        """recv(), after a send of `rows` to envs `ids` when given (one round trip)."""
        self._check_async("recv")
        if self._shared is not None:
            shared = self._shared
            shared.send(b"V", mask=None if rows is None else self._sent_mask(rows, ids))
            answer = shared.receive()
            ready = np.flatnonzero(shared.mask)
            terminated, truncated = shared.terminated[ready], shared.truncated[ready]
            ended = ready[terminated | truncated]
            return self._batch(ready, shared.obs[ready], shared.reward[ready], terminated, truncated, ended,
                               shared.final_obs[ended], shared.episode_return[ended], shared.episode_length[ended],
                               answer.errors)
        request = pb.RecvRequest(session_id=self.session_id)
        if rows is not None:
            request.actions.CopyFrom(_convert.to_tensor(rows))
            request.env_ids.extend(ids.tolist())
        response = self._transport.call("Recv", request)
        step = response.step
        return self._batch(
            np.array(response.env_ids, dtype=np.int64), _convert.to_numpy(step.obs).copy(),
            _convert.to_numpy(step.reward), np.array(step.terminated, dtype=bool), np.array(step.truncated, dtype=bool),
            *_ended_episodes(step))

    def _batch(self, ids, obs, rewards, terminated, truncated, ended, final_rows, returns, lengths, errors):
        """A recv's result as EnvPool returns it (rows in the order of `ids`), radserve's figures of the
        ended episodes (`ended`: their env ids, in the order of `final_rows`) as batch-row infos."""
        b = len(ids)
        infos: dict = {"env_id": ids.astype(np.int32)}
        if len(ended):
            row_of = {int(env): row for row, env in enumerate(ids)}
            rows = [row_of[int(env)] for env in ended]
            mask = np.zeros(b, dtype=bool)
            mask[rows] = True
            final = np.full(b, None, dtype=object)
            for k, row in enumerate(rows):
                final[row] = self._present(final_rows[k])
            infos.update({"final_obs": final, "_final_obs": mask})
            infos.update(episode_infos(b, rows, returns, lengths, {row_of[int(env)]: m for env, m in errors.items()}))
        if self._channels_last:
            obs = np.ascontiguousarray(np.moveaxis(obs, -3, -1))
        return obs, np.asarray(rewards, dtype=np.float64), terminated, truncated, infos

    def _check_idle(self, what: str) -> None:
        if self._pending is not None:
            raise RuntimeError(f"{what}() while a step_async() awaits its step_wait()")

    def _step_request(self, actions, skip=None) -> "pb.StepRequest":
        actions = self._in_action_dtype(actions)
        return pb.StepRequest(session_id=self.session_id, actions=_convert.to_tensor(actions), skip=_bools(skip))

    def _in_action_dtype(self, actions) -> np.ndarray:
        """`actions` as an array of the action dtype when they cast to it safely (else as given, for the
        server to refuse)."""
        actions = np.asarray(actions)
        if actions.dtype != self._action_dtype and np.can_cast(actions.dtype, self._action_dtype, "same_kind"):
            actions = actions.astype(self._action_dtype)
        return actions

    def _write_actions(self, actions) -> None:
        actions = np.asarray(actions)
        target = self._shared.actions
        if actions.shape != target.shape or not np.can_cast(actions.dtype, target.dtype, "same_kind"):
            raise InvalidArgumentError(
                f"actions must be {target.dtype} of shape {list(target.shape)} ({self.num_envs} envs, each "
                f"{self.single_action_space}); got {actions.dtype} of shape {list(actions.shape)}"
            )
        np.copyto(target, actions, casting="same_kind")

    def _unpack_shared(self, answer: "Answer") -> "_Step":
        shared = self._shared
        terminated, truncated = shared.terminated.copy(), shared.truncated.copy()
        ended = np.flatnonzero(terminated | truncated)
        return _Step(shared.obs.copy(), shared.reward.copy(), terminated, truncated, ended,
                     shared.final_obs[ended].copy(), shared.episode_return[ended].copy(),
                     shared.episode_length[ended].copy(), answer.errors, answer.step_infos, answer.reset_infos)

    def _unpack(self, response: "pb.StepResponse") -> "_Step":
        return _Step(
            # A copy, writable as gymnasium's are (its wrappers write into observations in place).
            _convert.to_numpy(response.obs).copy(), _convert.to_numpy(response.reward),
            np.array(response.terminated, dtype=bool), np.array(response.truncated, dtype=bool),
            *_ended_episodes(response),
            response.step_infos, response.reset_infos,
        )

    def _finish(self, step: "_Step"):
        """The step as this env's autoreset mode returns it, from the server's same-step result, with
        the envs' infos batched as gymnasium's SyncVectorEnv batches them in that mode."""
        obs = step.obs
        rows = {int(i): row for row, i in enumerate(step.ended)}
        infos = None
        if not rows and not step.reset_infos and not self._ended.any():
            # No episode ended, none restarts: gymnasium's infos are the step's, made from the columns.
            infos = vector_infos(step.step_infos, self.num_envs)
        if infos is None:
            infos = self._env_by_env_infos(step, rows)
        if len(step.ended):
            infos.update(episode_infos(self.num_envs, step.ended, step.returns, step.lengths, step.errors))
        if self.autoreset_mode != AutoresetMode.SAME_STEP:
            self._server_obs = obs
            if len(step.ended):
                obs = obs.copy()
                for row, i in enumerate(step.ended):
                    obs[i] = step.final_rows[row]
            self._ended = step.terminated | step.truncated
        self._last_obs = obs
        return self._present(obs) if self._channels_last else obs, step.rewards, step.terminated, step.truncated, infos

    def _env_by_env_infos(self, step: "_Step", rows: "dict[int, int]") -> dict:
        """The step's infos batched env by env as gymnasium's SyncVectorEnv batches them in this env's
        mode, from each env's dicts: the step's, the ended episodes' last observations and infos, the
        resets' (NEXT_STEP: held until the env's reset step)."""
        infos: dict = {}
        step_infos, reset_infos = env_infos(step.step_infos), env_infos(step.reset_infos)
        # Consecutive envs whose one info is flat are added together (add_flat); the run is
        # flushed before anything else is added, so that values arrive in gymnasium's order.
        run: "list[tuple[int, dict]]" = []

        def add(infos: dict, info: dict, i: int) -> dict:
            if run:
                infos = add_flat(infos, run, self.num_envs, self._add_info)
                run.clear()
            return self._add_info(infos, info, i)

        def add_step_info(infos: dict, info: dict, i: int) -> dict:
            if is_flat(info):
                run.append((i, info))
                return infos
            return add(infos, info, i)

        # Only envs with something to report (an empty info adds nothing), in env order as gymnasium's.
        for i in sorted(step_infos.keys() | reset_infos.keys() | rows.keys() | set(np.flatnonzero(self._ended).tolist())):
            step_info, reset_info = step_infos.get(i, {}), reset_infos.get(i)
            if self.autoreset_mode == AutoresetMode.SAME_STEP:
                if i in rows:
                    # gymnasium 1.x: the ended episode's last observation and info, then the reset's info.
                    final = {"final_obs": self._present(step.final_rows[rows[i]]), "final_info": step_info}
                    infos = add(infos, final, i)
                    infos = add(infos, reset_info or {}, i)
                else:
                    infos = add_step_info(infos, step_info, i)
            elif self._ended[i]:
                # NEXT_STEP's reset step: the info of the reset the server made a step ago.
                infos = add(infos, self._held_reset_infos.pop(i, None) or {}, i)
            else:
                infos = add_step_info(infos, step_info, i)
                if i in rows:
                    self._held_reset_infos[i] = reset_info
        if run:
            infos = add_flat(infos, run, self.num_envs, self._add_info)
        return infos

    def _acting_sessions(self):
        return [(self._transport, self.session_id, self.num_envs, 0)]

    def describe(self) -> "list[SessionInfo | None]":
        """The session as the server sees it (steps taken, episodes completed, options, its replay
        and actor): a list of one, as a sharded env's has one per server."""
        return [SessionInfo.from_proto(
            self._transport.call("DescribeSession", pb.DescribeSessionRequest(session_id=self.session_id)))]

    def _open_batches(self, request: "pb.SampleBatchesRequest", delivery: str):
        return open_batch_stream(self._transport, request, delivery)

    def close(self, *, timeout: "float | None" = None, discard_snapshot: bool = False, **kwargs):
        """Closes the session on the server (waiting at most `timeout` s for it to answer). A named
        session's replay gets a last snapshot, unless `discard_snapshot` removes its snapshot."""
        if self.closed:
            return
        self.closed = True
        if self._shared is not None:
            self._shared.close()
        if self._requests is not None:
            self._requests.put(None)
        try:
            self._transport.close_session(self.session_id, timeout=timeout, discard_snapshot=discard_snapshot)
        except Exception:  # the server may already be gone; closing must not raise
            pass


def open_vector_env(transport: Transport, request: "pb.CreateSessionRequest", **settings) -> RemoteVectorEnv:
    """A new session on one server, as a RemoteVectorEnv (`settings`: its keyword arguments)."""
    info = SessionInfo.from_proto(transport.create_session(request))
    try:
        return RemoteVectorEnv(transport, info, **settings)
    except BaseException:
        transport.close_session(info.session_id)  # the session would otherwise outlive the failed env
        raise
