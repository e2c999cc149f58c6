"""The client end of a shared-stepping channel (rpc ShareActing; protocol in the proto's
SharedActingChannel): actions are written into memory the server maps, a 16-byte request goes over
a Unix socket, and after an 8-byte answer the results are read where the server wrote them."""

import struct
from typing import NamedTuple

import numpy as np

from ._proto import radserve_pb2 as pb
from ._shm import receive_server_memory
from .errors import UnavailableError, from_status

_MAGIC = b"radserve-acting\0"  # the wire's magic, unchanged since v1
_REQUEST = struct.Struct("<cBB5xQ")
_ANSWER = struct.Struct("<II")
# An OK answer's records: env index, kind, length of the bytes that follow: kind 0 an env's simulator
# error (UTF-8), 1 and 2 the step's and the resets' infos (an encoded InfoColumns).
_RECORD = struct.Struct("<IBI")
_ERROR, _STEP_INFOS, _RESET_INFOS = 0, 1, 2


class Answer(NamedTuple):
    """An OK answer's records: the simulator errors of ended episodes by env, and the step's and the
    resets' info columns (as StepResponse's step_infos and reset_infos)."""

    errors: "dict[int, str]"
    step_infos: list
    reset_infos: list
_HINT = ("shared stepping needs the client on the server's host, in its network namespace, as a user the "
         "server allows; use delivery='grpc' otherwise")


class SharedStepping:
    """Arrays over the channel's memory, and the socket that says when they may be read."""

    def __init__(self, channel: "pb.SharedActingChannel", num_envs: int, obs_space, action_dtype, action_shape,
                 explain_loss=None):
        # When the channel ends under a call (the server closes it with its session), this says why:
        # the error the server gives for the session over gRPC, or None.
        self._explain_loss = explain_loss
        # The same connection carries the memory's descriptor, then the doorbells.
        self._memory, self._socket = receive_server_memory(
            channel.socket, channel.token, channel.size, _MAGIC, "shared-stepping memory", _HINT)
        n = num_envs
        obs_dtype = np.dtype(obs_space.dtype)

        def array(offset, shape, dtype):
            return np.ndarray(shape, dtype=dtype, buffer=self._memory, offset=offset)

        self.actions = array(channel.actions_offset, (n,) + tuple(action_shape), action_dtype)
        self.obs = array(channel.obs_offset, (n,) + obs_space.shape, obs_dtype)
        self.final_obs = array(channel.final_obs_offset, (n,) + obs_space.shape, obs_dtype)
        self.reward = array(channel.reward_offset, (n,), np.dtype("<f8"))
        self.terminated = array(channel.terminated_offset, (n,), np.bool_)
        self.truncated = array(channel.truncated_offset, (n,), np.bool_)
        self.episode_return = array(channel.episode_return_offset, (n,), np.dtype("<f8"))
        self.episode_length = array(channel.episode_length_offset, (n,), np.dtype("<u8"))
        self.mask = array(channel.mask_offset, (n,), np.bool_)
        self.env_seeds = array(channel.env_seeds_offset, (n,), np.dtype("<u8"))

    def send(self, kind: bytes, seed: "int | None" = None, mask=None, env_seeds=None) -> None:
        """Asks for a step (b"S", after writing `actions`; `mask`: envs not to step) or a reset (b"R";
        `mask`: only these envs, `env_seeds`: one seed per env)."""
        flags = 0
        if mask is not None:
            self.mask[:] = mask
            flags |= 1
        if env_seeds is not None:
            self.env_seeds[:] = env_seeds
            flags |= 2
        try:
            self._socket.sendall(_REQUEST.pack(kind, seed is not None, flags, seed or 0))
        except OSError as error:
            raise self._lost(f"the server's shared-stepping channel is gone: {error}") from None

    def receive(self) -> Answer:
        """Waits for the answer to the request sent and returns its records, or raises the server's
        error."""
        code, length = _ANSWER.unpack(self._read(_ANSWER.size))
        body = self._read(length) if length else b""
        if code != 0:
            raise from_status(code, body.decode("utf-8", "replace"))
        answer = Answer({}, [], [])
        at = 0
        while at < len(body):
            env, kind, size = _RECORD.unpack_from(body, at)
            at += _RECORD.size
            if kind == _ERROR:
                answer.errors[env] = body[at:at + size].decode("utf-8", "replace")
            elif kind == _STEP_INFOS:
                answer.step_infos.extend(pb.InfoColumns.FromString(body[at:at + size]).columns)
            elif kind == _RESET_INFOS:
                answer.reset_infos.extend(pb.InfoColumns.FromString(body[at:at + size]).columns)
            at += size
        return answer

    def _read(self, size: int) -> bytes:
        data = b""
        while len(data) < size:
            try:
                more = self._socket.recv(size - len(data))
            except OSError as error:
                raise self._lost(f"the server's shared-stepping channel failed: {error}") from None
            if not more:
                raise self._lost("the server closed the shared-stepping channel (it stopped, or the session was closed)")
            data += more
        return data

    def _lost(self, message: str) -> Exception:
        """The error for a channel that ended: the session's own (closed: NotFoundError), else
        UnavailableError with `message`."""
        reason = self._explain_loss() if self._explain_loss is not None else None
        return reason if reason is not None else UnavailableError(message)

    def close(self) -> None:
        """Ends the channel; the server frees it when it sees the socket close."""
        self._socket.close()
        for name in ("actions", "obs", "final_obs", "reward", "terminated", "truncated", "episode_return",
                     "episode_length", "mask", "env_seeds"):
            self.__dict__.pop(name, None)
        try:
            self._memory.close()
        except BufferError:  # an array over the memory is still referenced somewhere; it stays mapped
            pass

