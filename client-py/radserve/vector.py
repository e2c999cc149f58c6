"""A radserve session as a gymnasium VectorEnv."""

import queue
from typing import Any

import grpc
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from . import _convert
from ._acting import SharedActing
from ._proto import radserve_pb2 as pb
from .errors import InvalidArgumentError, RadServeError, SharedMemoryError, from_rpc_error

DELIVERIES = ("grpc", "shared_memory", "auto")


class RemoteVectorEnv(VectorEnv):
    """`num_envs` environments living in a radserve server, stepped together.

    Autoreset is same-step (`metadata["autoreset_mode"] == AutoresetMode.SAME_STEP`): when an
    episode ends, the returned observation of that env already starts the next episode, and
    `infos["final_obs"][i]` holds the last observation of the ended one (`infos["_final_obs"]` is
    the mask). `infos["episode"]` carries the return `r` and length `l` of ended episodes, and
    `infos["error"]` the simulator's message when it raised or its worker died.

    Delivery: "grpc" acts through unary calls (or one bidirectional stream with `stream=True`);
    "shared_memory" acts through memory shared with a server on the same host (rpc ShareActing: the
    actions and results never become messages, a 16-byte request per step goes over a Unix socket);
    "auto" uses shared memory when it can be mapped and gRPC otherwise. `delivery` says which is used.

    Over gRPC observations are read-only numpy arrays over the received message bytes (copy them to
    modify); through shared memory they are this env's own copies.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, client, info, *, stream: bool = False, delivery: str = "grpc"):
        if delivery not in DELIVERIES:
            raise ValueError(f"delivery must be one of {DELIVERIES}, got {delivery!r}")
        self._client = client
        self.info = info
        self.session_id = info.session_id
        self.num_envs = info.num_envs
        self.single_observation_space = info.observation_space
        self.single_action_space = info.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._action_dtype = np.dtype(np.int64) if info.action_space.shape == () else info.action_space.dtype
        self._requests: "queue.Queue | None" = None
        self._responses = None
        self._pending = None  # the step sent by step_async, until step_wait takes its reply
        self._shared: "SharedActing | None" = None
        if delivery != "grpc":
            channel = client._call("ShareActing", pb.ShareActingRequest(session_id=self.session_id))
            action_shape = () if info.action_space.shape == () else info.action_space.shape
            try:
                self._shared = SharedActing(
                    channel, self.num_envs, self.single_observation_space, self._action_dtype, action_shape,
                    explain_loss=self._session_error,
                )
            except SharedMemoryError:
                if delivery == "shared_memory":
                    raise
        self.delivery = "grpc" if self._shared is None else "shared_memory"
        if stream and self._shared is None:
            self._requests = queue.Queue()
            self._responses = client._stub.Act(iter(self._requests.get, None))
        self.closed = False

    def _session_error(self) -> "Exception | None":
        """What the server says of this session now (NotFoundError once it is closed), or None."""
        try:
            self._client._call("DescribeSession", pb.DescribeSessionRequest(session_id=self.session_id))
        except RadServeError as error:
            return error
        return None

    def _act(self, request: "pb.ActRequest", kind: str):
        if self._requests is None:
            method = "Reset" if kind == "reset" else "Step"
            return self._client._call(method, getattr(request, kind))
        self._requests.put(request)
        try:
            return getattr(next(self._responses), kind)
        except grpc.RpcError as error:
            raise from_rpc_error(error) from None

    def reset(self, *, seed: "int | list[int | None] | None" = None, options: "dict[str, Any] | None" = None):
        """Resets every environment; with `seed`, environment i is re-seeded with `seed + i`.

        As in gymnasium, `seed` may also be a list of one seed per env; radserve seeds env i with
        s + i, so the list must be [s, s + 1, ..., s + n - 1] (or all None: no reseeding)."""
        self._check_idle("reset")
        seed = self._session_seed(seed)
        if self._shared is not None:
            self._shared.send(b"R", seed)
            self._shared.receive()
            return self._shared.obs.copy(), {}
        request = pb.ResetRequest(session_id=self.session_id, seed=seed)
        response = self._act(pb.ActRequest(reset=request), "reset")
        return _convert.to_numpy(response.obs), {}

    def _session_seed(self, seed) -> "int | None":
        """The session seed that `seed` (an int, None, or one per env) stands for, checked."""
        if seed is None:
            return None
        if isinstance(seed, (list, tuple, np.ndarray)):
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise InvalidArgumentError(f"reset got {len(seeds)} seeds for {self.num_envs} envs")
            if all(entry is None for entry in seeds):
                return None
            first = seeds[0]
            if not all(isinstance(entry, (int, np.integer)) for entry in seeds) \
                    or any(int(entry) != int(first) + i for i, entry in enumerate(seeds)):
                raise InvalidArgumentError(
                    f"radserve seeds env i with seed + i: a list of seeds must be [s, s + 1, ..., s + "
                    f"{self.num_envs - 1}] (or all None), got {seeds}")
            seed = first
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise InvalidArgumentError(f"seed must be an int, a list of ints or None, got {seed!r}")
        if not 0 <= int(seed) < 1 << 64:
            raise InvalidArgumentError(f"seed must be a non-negative integer, got {seed}")
        return int(seed)

    def step(self, actions):
        self._check_idle("step")
        if self._shared is not None:
            self._write_actions(actions)
            self._shared.send(b"S")
            return self._unpack_shared(self._shared.receive())
        return self._unpack(self._act(pb.ActRequest(step=self._step_request(actions)), "step"))

    def step_async(self, actions) -> None:
        """Sends a step and returns at once; `step_wait()` returns what `step(actions)` would have.

        This is EnvPool's send/recv split, for pipelining: a learner holding two sessions sends one's
        step, then works on the other's observations while the server steps the first, so neither
        the workers nor the learner wait for each other. One step may be outstanding per session.
        Errors (a wrong action shape, an unknown session) are raised by `step_wait()`."""
        self._check_idle("step_async")
        if self._shared is not None:
            self._write_actions(actions)
            self._shared.send(b"S")
            self._pending = self._shared
            return
        request = self._step_request(actions)
        if self._requests is None:
            self._pending = self._client._stub.Step.future(request)
        else:
            self._requests.put(pb.ActRequest(step=request))
            self._pending = self._responses

    def step_wait(self):
        """The reply to the step sent by `step_async()`."""
        if self._pending is None:
            raise RuntimeError("step_wait() without a step_async() before it")
        pending, self._pending = self._pending, None
        if self._shared is not None:
            return self._unpack_shared(self._shared.receive())
        try:
            response = pending.result() if self._requests is None else next(pending).step
        except grpc.RpcError as error:
            raise from_rpc_error(error) from None
        return self._unpack(response)

    def _check_idle(self, what: str) -> None:
        if self._pending is not None:
            raise RuntimeError(f"{what}() while a step_async() awaits its step_wait()")

    def _step_request(self, actions) -> "pb.StepRequest":
        actions = np.asarray(actions)
        if actions.dtype != self._action_dtype and np.can_cast(actions.dtype, self._action_dtype, "same_kind"):
            actions = actions.astype(self._action_dtype)
        return pb.StepRequest(session_id=self.session_id, actions=_convert.to_tensor(actions))

    def _write_actions(self, actions) -> None:
        actions = np.asarray(actions)
        target = self._shared.actions
        if actions.shape != target.shape or not np.can_cast(actions.dtype, target.dtype, "same_kind"):
            raise InvalidArgumentError(
                f"actions must be {target.dtype} of shape {list(target.shape)} ({self.num_envs} envs, each "
                f"{self.single_action_space}); got {actions.dtype} of shape {list(actions.shape)}"
            )
        np.copyto(target, actions, casting="same_kind")

    def _unpack_shared(self, errors: "dict[int, str]"):
        shared = self._shared
        terminated, truncated = shared.terminated.copy(), shared.truncated.copy()
        ended = np.flatnonzero(terminated | truncated)
        infos = {}
        if len(ended):
            infos = self._episode_infos(
                ended, shared.final_obs[ended], shared.episode_return[ended], shared.episode_length[ended], errors
            )
        return shared.obs.copy(), shared.reward.copy(), terminated, truncated, infos

    def _unpack(self, response: "pb.StepResponse"):
        obs = _convert.to_numpy(response.obs)
        rewards = _convert.to_numpy(response.reward)
        terminated = np.array(response.terminated, dtype=bool)
        truncated = np.array(response.truncated, dtype=bool)
        return obs, rewards, terminated, truncated, self._infos(response)

    def _infos(self, response: "pb.StepResponse") -> dict:
        if not response.episodes:
            return {}
        episodes = response.episodes
        return self._episode_infos(
            [episode.env_index for episode in episodes],
            _convert.to_numpy(response.final_obs),
            [episode.episode_return for episode in episodes],
            [episode.episode_length for episode in episodes],
            {episode.env_index: episode.error for episode in episodes if episode.error},
        )

    def _episode_infos(self, envs, final_rows, episode_returns, episode_lengths, errors: "dict[int, str]") -> dict:
        """gymnasium's infos for the episodes that ended: env `envs[k]` ended with `final_rows[k]`."""
        n = self.num_envs
        mask = np.zeros(n, dtype=bool)
        final_obs = np.full(n, None, dtype=object)
        final_info = np.full(n, None, dtype=object)
        returns = np.zeros(n, dtype=np.float64)
        lengths = np.zeros(n, dtype=np.int64)
        for row, i in enumerate(envs):
            mask[i] = True
            final_obs[i] = final_rows[row]
            returns[i], lengths[i] = episode_returns[row], episode_lengths[row]
            final_info[i] = {"episode": {"r": returns[i], "l": lengths[i]}}
            if i in errors:
                final_info[i]["error"] = errors[i]
        infos = {
            "final_obs": final_obs,
            "_final_obs": mask,
            "final_info": final_info,
            "_final_info": mask.copy(),
            "episode": {"r": returns, "l": lengths, "_r": mask.copy(), "_l": mask.copy()},
            "_episode": mask.copy(),
        }
        if errors:
            error_array = np.full(n, None, dtype=object)
            for i, message in errors.items():
                error_array[i] = message
            infos["error"] = error_array
            infos["_error"] = np.array([e is not None for e in error_array])
        return infos

    def describe(self):
        """The session as the server sees it (steps taken, episodes completed, options)."""
        return self._client.describe_session(self.session_id)

    def close(self, **kwargs):
        if self.closed:
            return
        self.closed = True
        if self._shared is not None:
            self._shared.close()
        if self._requests is not None:
            self._requests.put(None)
        try:
            self._client.close_session(self.session_id)
        except Exception:  # the server may already be gone; closing must not raise
            pass
