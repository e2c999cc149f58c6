"""Server-side actors: send the server a policy (an ONNX model, or a torch module exported to one) and
let it step the session's envs, so the learner only streams batches.

    envs = client.make_vec("dmc/cartpole-swingup", num_envs=8, replay_capacity=100_000,
                           observation_view="center_crop(84)")
    envs.set_policy(actor, example_obs, head="gaussian_tanh")      # torch module: exported here
    envs.start_acting(random_steps=1000, samples_per_insert=..., min_size=1000)
    for batch in envs.sample_batches(256, ...):                    # batch.policy_version: staleness
        ...update...
        if update % 10 == 0:
            envs.set_policy(actor, example_obs)                   # next version, taken between steps
    envs.stop_acting()

Every call that goes to the env's servers (set_policy, start_acting, stop_acting, acting,
wait_acting) returns a list in server order, one answer per server: one item for a plain env, one
per shard for a sharded one, None for a server lost now.

Heads (see the proto's PolicyHead): "gaussian_tanh" (outputs mean, log_std), "categorical" (logits,
optionally value), "deterministic_noise" (action in [-1, 1]; `noise=(std_start, std_end, std_steps,
clip)`, DrQ-v2's schedule).
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass, field
from typing import Any

from ._proto import radserve_pb2 as pb
from .errors import InvalidArgumentError

HEADS = {
    "gaussian_tanh": pb.POLICY_HEAD_GAUSSIAN_TANH,
    "categorical": pb.POLICY_HEAD_CATEGORICAL,
    "deterministic_noise": pb.POLICY_HEAD_DETERMINISTIC_NOISE,
}


@dataclass(frozen=True)
class ActingInfo:
    """A session's server-side actor, as DescribeSession, StartActing and StopActing report it."""

    state: str
    """"idle", "acting", "stopped" (StopActing, or max_episodes/max_env_steps reached), "failed" """
    policy_version: "int | None"
    acting_version: "int | None"
    head: str
    env_steps: int
    episodes: int
    recent_returns: "list[float]" = field(default_factory=list)
    inference_seconds: float = 0.0
    step_seconds: float = 0.0
    limited_seconds: float = 0.0
    error: str = ""
    recent_envs: "list[int]" = field(default_factory=list)
    """the env (index in this server's session) each of `recent_returns` ended in"""

    @staticmethod
    def from_proto(message: "pb.ActingInfo") -> "ActingInfo":
        return ActingInfo(
            state=message.state,
            policy_version=message.policy_version if message.HasField("policy_version") else None,
            acting_version=message.acting_version if message.HasField("acting_version") else None,
            head=message.head,
            env_steps=message.env_steps,
            episodes=message.episodes,
            recent_returns=list(message.recent_returns),
            inference_seconds=message.inference_seconds,
            step_seconds=message.step_seconds,
            limited_seconds=message.limited_seconds,
            error=message.error,
            recent_envs=list(message.recent_envs),
        )


@dataclass(frozen=True)
class LoadedPolicy:
    """What the server read of a model it accepted (SetPolicy's answer)."""

    version: int
    ops: "list[str]"
    opset: int
    input: str
    outputs: "list[str]"
    has_value: bool


def export_onnx(module: Any, example_obs: Any, *, opset: int = 17) -> bytes:
    """A torch module (obs -> the head's outputs) as ONNX bytes with a dynamic batch axis. The module
    takes observations as the session returns them, converted to float32 (raw 0..255 pixels: divide
    by 255 inside, as RAD's encoder does); `example_obs` is one batch of them (any batch size)."""
    import torch  # the learners' extra; only this function needs it

    example = torch.as_tensor(example_obs, dtype=torch.float32)
    if example.dim() < 2:
        raise InvalidArgumentError(f"example_obs must be a batch [batch, *observation]; got shape {tuple(example.shape)}")
    was_training = module.training
    module.eval()
    buffer = io.BytesIO()
    try:
        with torch.no_grad():
            outputs = module(example)
        count = len(outputs) if isinstance(outputs, (tuple, list)) else 1
        names = [f"output{i}" for i in range(count)]
        torch.onnx.export(module, (example,), buffer, input_names=["obs"], output_names=names,
                          dynamic_axes={"obs": {0: "batch"}, **{name: {0: "batch"} for name in names}},
                          opset_version=opset, dynamo=False)
    finally:
        module.train(was_training)
    return buffer.getvalue()


def set_policy_request(session_id: str, model: bytes, head: str, version: int,
                       noise: "tuple[float, float, int, float] | None") -> "pb.SetPolicyRequest":
    if head not in HEADS:
        raise InvalidArgumentError(f"head must be one of {sorted(HEADS)}, got {head!r}")
    if not isinstance(version, int) or not 0 <= version < 1 << 31:
        raise InvalidArgumentError(f"version must be an int in [0, 2**31), got {version!r}")
    request = pb.SetPolicyRequest(session_id=session_id, model=bytes(model), head=HEADS[head], version=version)
    if noise is not None:
        if head != "deterministic_noise":
            raise InvalidArgumentError("noise is the deterministic_noise head's schedule")
        std_start, std_end, std_steps, clip = noise
        request.noise.CopyFrom(pb.NoiseSchedule(std_start=std_start, std_end=std_end, std_steps=int(std_steps), clip=clip))
    return request


def loaded(response: "pb.SetPolicyResponse") -> LoadedPolicy:
    return LoadedPolicy(version=response.version, ops=list(response.ops), opset=response.opset, input=response.input,
                        outputs=list(response.outputs), has_value=response.has_value)


def start_request(session_id: str, *, random_steps: int = 0, steps_per_second: "float | None" = None,
                  deterministic: bool = False, samples_per_insert: "float | None" = None, error_buffer: float = 0.0,
                  min_size: int = 0, seed: "int | None" = None, max_episodes: "int | None" = None,
                  max_env_steps: "int | None" = None) -> "pb.StartActingRequest":
    """StartActing's request. `deterministic` acts without exploration (tanh(mean), argmax, no
    noise: the proto's `eval`), for evaluation; `samples_per_insert`, `error_buffer` and `min_size`
    are Reverb's rate limiter against the learner's sampling."""
    request = pb.StartActingRequest(session_id=session_id, random_steps=int(random_steps), eval=bool(deterministic),
                                    error_buffer=float(error_buffer), min_size=int(min_size))
    if steps_per_second is not None:
        request.steps_per_second = float(steps_per_second)
    if samples_per_insert is not None:
        request.samples_per_insert = float(samples_per_insert)
    if seed is not None:
        request.seed = int(seed)
    if max_episodes is not None:
        request.max_episodes = int(max_episodes)
    if max_env_steps is not None:
        request.max_env_steps = int(max_env_steps)
    return request


class ActingMixin:
    """set_policy / start_acting / stop_acting / acting for a vector env whose sessions are
    `self._acting_sessions()`: (transport, session_id, num_envs, position) for each server it is
    served by now, out of `self._acting_servers` (a sharded env acts on every server it spans, with
    the same policy and version; a lost server is left out until it is back)."""

    _policy_version = 0
    _acting_servers = 1
    # The settings of the last start_acting while the actors act (a server that comes back is started
    # with them); None once stopped.
    _acting_settings: "dict | None" = None

    @property
    def policy_version(self) -> int:
        """The last version this env sent with set_policy (0: none)."""
        return self._policy_version

    def _acting_sessions(self):  # pragma: no cover - provided by the env
        raise NotImplementedError

    def _acting_returned(self) -> list:
        """Servers that came back since the last call, reconnected: (transport, session_id, num_envs,
        position) of their new sessions. A sharded env that goes on without a lost server says."""
        return []

    def _per_server(self, answers: "list[tuple[int, Any]]") -> list:
        """Answers by server position as a list in server order, None where a server gave none."""
        ordered: list = [None] * self._acting_servers
        for position, answer in answers:
            ordered[position] = answer
        return ordered

    def set_policy(self, policy: Any, example_obs: Any = None, *, head: str = "gaussian_tanh",
                   version: "int | None" = None,
                   noise: "tuple[float, float, int, float] | None" = None) -> "list[LoadedPolicy | None]":
        """Sends a policy: ONNX bytes, or a torch module exported with `example_obs` (a batch of
        observations). `version` defaults to one more than the last this env sent; a running actor
        takes the new version between two steps. Refused models raise InvalidArgumentError with the
        server's reason (the operator it does not support, the shape it expected). Returns what each
        server read of the model, in server order (None for a server lost now).

        On a sharded env that goes on without a lost server (`on_server_loss="continue"`), this is
        also when a lost server is tried again: one that is back gets a new session, this policy and,
        while the others act, their start_acting settings."""
        if isinstance(policy, (bytes, bytearray, memoryview)):
            model = bytes(policy)
        else:
            if example_obs is None:
                raise InvalidArgumentError("set_policy(module, example_obs): a torch module needs a batch of observations to export")
            model = export_onnx(policy, example_obs)
        version = self._policy_version + 1 if version is None else version
        returned = self._acting_returned()
        answers = [(position, loaded(transport.call("SetPolicy", set_policy_request(session_id, model, head, version, noise))))
                   for transport, session_id, _, position in self._acting_sessions()]
        self._policy_version = version
        # Only while the others act: an actor that ended on its own budget (a PPO rollout's
        # steps_per_env) is started again by the learner, which would find this one acting.
        if returned and self._acting_settings is not None and any(
                info is not None and info.state == "acting" for info in self._acting_answers()):
            for target in returned:
                self._start_on(target, self._acting_settings)
        return self._per_server(answers)

    @staticmethod
    def _start_on(target, settings: dict) -> "pb.ActingInfo":
        transport, session_id, num_envs, position = target
        settings = dict(settings)
        steps_per_env = settings.pop("steps_per_env", None)
        if settings.get("seed") is not None:
            settings["seed"] = int(settings["seed"]) + position
        if steps_per_env is not None:
            settings["max_env_steps"] = steps_per_env * num_envs
        return transport.call("StartActing", start_request(session_id, **settings))

    def start_acting(self, *, steps_per_env: "int | None" = None, **settings) -> "list[ActingInfo | None]":
        """Starts the server's actor on this env's session(s): see `radserve.actors.start_request` for
        the settings (random_steps, steps_per_second, deterministic, samples_per_insert,
        error_buffer, min_size, seed, max_episodes, max_env_steps; each server's own, a seed offset
        by the server's position). `steps_per_env=T` stops every env after T steps, one rollout of a
        PPO learner: `max_env_steps` of T times each server's envs. Step and reset are refused while
        it acts. Returns each server's actor as it started, in server order."""
        if steps_per_env is not None:
            if isinstance(steps_per_env, bool) or not isinstance(steps_per_env, int) or steps_per_env < 1:
                raise InvalidArgumentError(f"steps_per_env must be a positive integer, got {steps_per_env!r}")
            if settings.get("max_env_steps") is not None:
                raise InvalidArgumentError("give steps_per_env or max_env_steps, not both")
        if "eval" in settings:
            raise InvalidArgumentError("start_acting(eval=...) is start_acting(deterministic=...) since radserve 0.2.0")
        settings = dict(settings, steps_per_env=steps_per_env)
        answers = [(target[3], ActingInfo.from_proto(self._start_on(target, settings))) for target in self._acting_sessions()]
        self._acting_settings = settings
        return self._per_server(answers)

    def stop_acting(self) -> "list[ActingInfo | None]":
        """Stops the actor after its current step; the env is the learner's to step again. Returns
        each server's actor as it stopped, in server order."""
        self._acting_settings = None
        return self._per_server([
            (position, ActingInfo.from_proto(transport.call("StopActing", pb.StopActingRequest(session_id=session_id))))
            for transport, session_id, _, position in self._acting_sessions()])

    def acting(self) -> "list[ActingInfo | None]":
        """The actor on each server, in server order (None where no policy was ever set, and for a
        server lost now)."""
        return self._acting_answers()

    def wait_acting(self, timeout: "float | None" = None, *, env_steps: "int | None" = None,
                    episodes: "int | None" = None, poll: float = 0.05) -> "list[ActingInfo | None]":
        """Waits until no server's actor acts any more (each stopped: its max_env_steps or
        max_episodes reached, StopActing, or failed), or, given `env_steps` or `episodes`, until the
        actors have taken that many env steps or ended that many episodes since their start (summed
        over the servers). Returns the actors as `acting()` does. Raises RuntimeError when an actor
        failed (with the server's reason) and TimeoutError past `timeout` seconds."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            answers = self._acting_answers()
            infos = [info for info in answers if info is not None]
            failed = [info.error for info in infos if info.state == "failed"]
            if failed:
                raise RuntimeError(f"a server's actor failed: {failed[0]}")
            if not any(info.state == "acting" for info in infos):
                return answers
            if env_steps is not None and sum(info.env_steps for info in infos) >= env_steps:
                return answers
            if episodes is not None and sum(info.episodes for info in infos) >= episodes:
                return answers
            if deadline is not None and time.monotonic() >= deadline:
                raise TimeoutError(f"the actors still act after {timeout} s: {answers}")
            time.sleep(poll)

    def _acting_answers(self) -> "list[ActingInfo | None]":
        answers: "list[ActingInfo | None]" = [None] * self._acting_servers
        for transport, session_id, _, position in self._acting_sessions():
            info = transport.call("DescribeSession", pb.DescribeSessionRequest(session_id=session_id))
            answers[position] = ActingInfo.from_proto(info.acting) if info.HasField("acting") else None
        return answers
