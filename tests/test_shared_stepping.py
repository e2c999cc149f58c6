"""Shared stepping: a session reset and stepped through shared memory (rpc ShareActing): the same
results as gRPC, the same errors, and a server that keeps serving whatever a client does with the
channel. The env contract itself also runs through shared memory (test_conformance.py, the
*SharedMemory classes). The channel's socket over the fake simulators (a silent connection, a
session closed under its channel) is tested in server/radserve/tests/shared_stepping.rs."""

import mmap
import os
import signal
import socket
import struct
import subprocess
import sys
import time

import numpy as np
import pytest

import radserve
from radserve.proto import radserve_pb2 as pb
from _procs import worker_pids

REQUEST = struct.Struct("<cB6xQ")
ANSWER = struct.Struct("<II")
INVALID_ARGUMENT, FAILED_PRECONDITION, NOT_FOUND = 3, 9, 5


def assert_same_infos(want: dict, have: dict) -> None:
    """Every key, mask and value (final observations row by row, nested dicts recursively), dtypes too."""
    assert want.keys() == have.keys(), (want.keys(), have.keys())
    for key, value in want.items():
        if isinstance(value, dict):
            assert_same_infos(value, have[key])
        elif key == "final_obs":
            for i, row in enumerate(value):
                if row is None:
                    assert have[key][i] is None
                else:
                    np.testing.assert_array_equal(row, have[key][i])
        else:
            np.testing.assert_array_equal(value, have[key], err_msg=key)
            assert value.dtype == have[key].dtype, key


def assert_same_step(want, have):
    for a, b in zip(want[:4], have[:4]):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == b.dtype
    assert_same_infos(want[4], have[4])


@pytest.mark.parametrize(
    "env_id, options",
    [("gym/HalfCheetah-v5", {"max_episode_steps": 6}), ("dmc/cartpole-balance",
     {"height": 32, "width": 32, "render_profile": "fast", "action_repeat": 100, "frame_stack": 2})],
    ids=["gym", "dmc-pixels"],
)
def test_shared_memory_gives_what_grpc_gives_step_for_step(client, env_id, options):
    """Observations, rewards, flags, ended episodes' final observations, returns and lengths; also
    pipelined (step_async/step_wait) and after a reseeding reset."""
    grpc_envs = client.make_vec(env_id, num_envs=3, seed=7, **options)
    shared = client.make_vec(env_id, num_envs=3, seed=7, delivery="shared_memory", **options)
    try:
        assert shared.delivery == "shared_memory"
        np.testing.assert_array_equal(grpc_envs.reset()[0], shared.reset()[0])
        rng = np.random.default_rng(0)
        ended = 0
        for t in range(20):
            actions = rng.uniform(-1, 1, (3,) + shared.single_action_space.shape).astype(np.float32)
            want = grpc_envs.step(actions)
            if t % 2:
                have = shared.step(actions)
            else:
                shared.step_async(actions)
                have = shared.step_wait()
            assert_same_step(want, have)
            ended += int((want[2] | want[3]).sum())
        assert ended > 0  # episodes ended, so the final_obs path was compared
        np.testing.assert_array_equal(grpc_envs.reset(seed=3)[0], shared.reset(seed=3)[0])
        actions = np.zeros((3,) + shared.single_action_space.shape, np.float32)
        assert_same_step(grpc_envs.step(actions), shared.step(actions))
        # Results are the caller's own arrays: the next step does not change them.
        obs = shared.step(actions)[0]
        before = obs.copy()
        shared.step(actions + 0.5)
        np.testing.assert_array_equal(obs, before)
    finally:
        grpc_envs.close()
        shared.close()


def test_errors_are_the_same_and_change_nothing(client):
    envs = client.make_vec("gym/Pendulum-v1", num_envs=2, delivery="shared_memory")
    try:
        with pytest.raises(radserve.FailedPreconditionError, match="Reset"):
            envs.step(np.zeros((2, 1), np.float32))
        envs.reset()
        with pytest.raises(radserve.InvalidArgumentError, match=r"float32 of shape \[2, 1\].*got float64 of shape \[3, 1\]"):
            envs.step(np.zeros((3, 1)))
        with pytest.raises(radserve.InvalidArgumentError, match=r"outside \[-2, 2\]"):
            envs.step(np.array([[0.0], [7.0]], np.float32))
        with pytest.raises(radserve.InvalidArgumentError, match="seed"):
            envs.reset(seed=-1)
        assert envs.describe()[0].total_env_steps == 0
        assert envs.step(np.zeros((2, 1), np.float32))[0].shape == (2, 3)
        assert envs.describe()[0].total_env_steps == 2
    finally:
        envs.close()


def test_a_dead_worker_ends_its_episodes_with_the_reason(server, client, catalog):
    # `catalog` first: the transient worker that builds it must be gone before workers are counted.
    envs = client.make_vec("gym/HalfCheetah-v5", num_envs=2, seed=0, delivery="shared_memory", autoreset_mode="SameStep")
    try:
        envs.reset()
        os.kill(worker_pids(server.process.pid)[0], signal.SIGKILL)
        time.sleep(0.2)
        _, _, _, truncated, infos = envs.step(np.zeros((2, 6), np.float32))
        assert truncated.sum() == 1
        i = int(np.flatnonzero(truncated)[0])
        assert "died" in infos["radserve_error"][i] and infos["_final_info"][i]
        assert infos["final_obs"][i].shape == (17,)
        envs.step(np.zeros((2, 6), np.float32))
    finally:
        envs.close()


def _connect(channel: "pb.SharedActingChannel", token: bytes) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(20)
    sock.connect("\0" + channel.socket)
    sock.sendall(token)
    return sock


def _ask(sock, request: bytes):
    sock.sendall(request)
    code, length = ANSWER.unpack(sock.recv(8, socket.MSG_WAITALL))
    return code, sock.recv(length, socket.MSG_WAITALL).decode() if length else ""


def test_the_raw_protocol_answers_malformed_requests_and_checks_the_token(client):
    envs = client.make_vec("gym/CartPole-v1", num_envs=2)
    try:
        channel = client.transports[0].stub.ShareActing(pb.ShareActingRequest(session_id=envs.session_id))
        assert channel.size > channel.episode_length_offset and len(channel.token) == 16
        # One channel per session at a time.
        with pytest.raises(radserve.FailedPreconditionError, match="already has"):
            client.transports[0].call("ShareActing", pb.ShareActingRequest(session_id=envs.session_id))
        # A connection without the token is dropped; the rightful client can still take the channel.
        stranger = _connect(channel, b"x" * 16)
        assert stranger.recv(1) == b""
        sock = _connect(channel, channel.token)
        # The server hands over the memory itself: one byte and its descriptor, nothing by name.
        handed, fds, _, _ = socket.recv_fds(sock, 1, 1)
        assert handed == b"\x01" and len(fds) == 1
        memory = mmap.mmap(fds[0], channel.size)
        os.close(fds[0])
        assert memory[:16] == b"radserve-acting\0" and memory[16:32] == channel.token
        assert _ask(sock, REQUEST.pack(b"X", 0, 0))[0] == INVALID_ARGUMENT
        code, message = _ask(sock, REQUEST.pack(b"R", 7, 0))
        assert code == INVALID_ARGUMENT and "0 or 1" in message
        assert _ask(sock, REQUEST.pack(b"R", 0, 0)) == (0, "")
        # The memory holds the reset's observations, as the gRPC reset would return them.
        obs = np.ndarray((2, 4), np.float32, buffer=memory, offset=channel.obs_offset).copy()
        assert np.all(np.abs(obs) <= 0.05)  # CartPole starts near the origin
        actions = np.ndarray((2,), np.int64, buffer=memory, offset=channel.actions_offset)
        actions[:] = [5, 0]
        code, message = _ask(sock, REQUEST.pack(b"S", 0, 0))
        assert code == INVALID_ARGUMENT and "outside" in message
        actions[:] = [1, 0]
        assert _ask(sock, REQUEST.pack(b"S", 0, 0)) == (0, "")
        assert envs.describe()[0].total_env_steps == 2
        # EnvPool's asynchronous requests: malformed ones, then refused on a synchronous session.
        flagged = struct.Struct("<cBB5xQ")  # kind, has-seed, flags (1: mask, 2: per-env seeds), seed
        code, message = _ask(sock, flagged.pack(b"A", 0, 1, 0))
        assert code == INVALID_ARGUMENT and "no mask" in message
        code, message = _ask(sock, flagged.pack(b"E", 0, 0, 0))
        assert code == INVALID_ARGUMENT and "mask array" in message
        code, message = _ask(sock, flagged.pack(b"V", 1, 0, 3))
        assert code == INVALID_ARGUMENT and "no seed" in message
        code, message = _ask(sock, flagged.pack(b"V", 0, 0, 0))
        assert code == INVALID_ARGUMENT and "steps every env at once" in message
        assert envs.describe()[0].total_env_steps == 2
        del obs, actions
        memory.close()
        # The channel ends with its connection; then the session can open another.
        sock.close()
        for _ in range(100):
            try:
                client.transports[0].call("ShareActing", pb.ShareActingRequest(session_id=envs.session_id))
                break
            except radserve.FailedPreconditionError:
                time.sleep(0.05)
        else:
            pytest.fail("the channel was not freed after its client disconnected")
    finally:
        envs.close()


def test_unknown_or_closed_sessions(client):
    with pytest.raises(radserve.NotFoundError, match="unknown session"):
        client.transports[0].call("ShareActing", pb.ShareActingRequest(session_id="nope"))
    envs = client.make_vec("gym/CartPole-v1", num_envs=1, delivery="shared_memory")
    envs.reset()
    client.close_session(envs.session_id)
    with pytest.raises(radserve.NotFoundError, match="unknown session"):
        envs.step(np.zeros(1, np.int64))
    envs.close()


# A client run as another user (nobody): handed no memory, since the server allows its own uid and
# server.shared_memory_uids only.
_STRANGER_CLIENT = """
import sys
import numpy as np
import radserve
with radserve.Client(sys.argv[1]) as client:
    envs = client.make_vec("gym/CartPole-v1", num_envs=1, delivery="auto")
    assert envs.delivery == "grpc", envs.delivery
    envs.reset()
    assert envs.step(np.zeros(1, np.int64))[0].shape == (1, 4)
    envs.close()
    try:
        client.make_vec("gym/CartPole-v1", num_envs=1, delivery="shared_memory")
    except radserve.SharedMemoryError as error:
        print("refused:", error)
    else:
        raise SystemExit("the server handed its memory to another user")
"""


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to run the client as another user")
def test_auto_falls_back_to_grpc_where_memory_cannot_be_mapped(server, client):
    result = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", "--", sys.executable,
                             "-c", _STRANGER_CLIENT, server.address], capture_output=True, text=True, timeout=120,
                            env={**os.environ, "HOME": "/tmp"})
    assert result.returncode == 0, result.stdout + result.stderr
    assert "refused:" in result.stdout and "delivery='grpc'" in result.stdout, result.stdout
    # The server's own user gets the memory.
    envs = client.make_vec("gym/CartPole-v1", num_envs=1, delivery="auto")
    assert envs.delivery == "shared_memory"
    envs.close()
    with pytest.raises(ValueError, match="delivery"):
        client.make_vec("gym/CartPole-v1", num_envs=1, delivery="carrier pigeon")


# A process of the server's own user, without the capabilities root has (CAP_SYS_PTRACE opens any
# /proc/<pid>/fd): lists and opens every descriptor of the given processes, prints how many it mapped.
_PROC_PROBE = """
import mmap, os, sys
mapped = 0
for pid in sys.argv[1:]:
    try:
        names = os.listdir(f"/proc/{pid}/fd")
    except (PermissionError, FileNotFoundError):  # protected, or gone (a transient worker is killed)
        continue
    for name in names:
        path = f"/proc/{pid}/fd/{name}"
        try:
            if "memfd:" not in os.readlink(path):
                continue
            fd = os.open(path, os.O_RDWR)
        except OSError:
            continue
        if os.fstat(fd).st_size:  # an empty memfd cannot be mapped, but opening it was the breach
            mmap.mmap(fd, 0).close()
        mapped += 1
print(mapped)
"""


def _without_capabilities(command: "list[str]") -> "list[str]":
    """`command` as the same user without root's capabilities (as root, CAP_SYS_PTRACE opens every
    /proc/<pid>/fd, whatever the process did): setpriv execs it, so its pid stays the same."""
    if os.geteuid() != 0:
        return command
    return ["setpriv", "--inh-caps=-all", "--ambient-caps=-all", "--bounding-set=-all", "--", *command]


def test_other_processes_of_the_same_user_cannot_map_the_memory_by_proc():
    """The old way in (`/proc/<server pid>/fd/N`, and the workers' frames the same way) is closed: the
    server and its workers are non-dumpable, so only the client the memory was handed to maps it."""
    server = radserve.LocalServer(workers=1)
    server.args = _without_capabilities(server.args)
    # A control: a process of the same kind that did not protect itself, holding a memfd.
    holder = subprocess.Popen(_without_capabilities([sys.executable, "-c", (
        "import os, time; fd = os.memfd_create('control'); os.ftruncate(fd, 4096); print('ready', flush=True); "
        "time.sleep(120)")]), stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "ready"
        with server, radserve.Client(server.address) as client:
            envs = client.make_vec("gym/CartPole-v1", num_envs=1, delivery="shared_memory")
            envs.reset()
            pids = [server.process.pid, *worker_pids(server.process.pid)]
            assert len(pids) >= 2

            def probe(*targets) -> int:
                result = subprocess.run(_without_capabilities([sys.executable, "-c", _PROC_PROBE, *map(str, targets)]),
                                        capture_output=True, text=True, timeout=60)
                assert result.returncode == 0, result.stderr
                return int(result.stdout)

            assert probe(holder.pid) == 1, "the probe maps the memfd of a process that did not protect itself"
            assert probe(*pids) == 0, "another process mapped radserve's memory through /proc"
            # The rightful client still acts through the memory it was handed.
            assert envs.step(np.zeros(1, np.int64))[0].shape == (1, 4)
            envs.close()
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to run a process as another user")
def test_another_user_gets_no_descriptor_even_with_the_token(client):
    """SO_PEERCRED: a connection from a uid the server does not allow is dropped before it is read,
    so even the right token (which another user could only have stolen) hands nothing over."""
    envs = client.make_vec("gym/CartPole-v1", num_envs=1)
    try:
        channel = client.transports[0].stub.ShareActing(pb.ShareActingRequest(session_id=envs.session_id))
        stranger = "\n".join([
            "import socket, sys",
            "s = socket.socket(socket.AF_UNIX)",
            "s.connect('\\0' + sys.argv[1])",
            "s.settimeout(10)",
            "try:",
            "    s.sendall(bytes.fromhex(sys.argv[2]))",
            "    data, fds, _, _ = socket.recv_fds(s, 1, 1)",
            "    print(len(data), len(fds))",
            "except (BrokenPipeError, ConnectionResetError):",
            "    print(0, 0)",
        ])
        result = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", "--", sys.executable,
                                 "-c", stranger, channel.socket, channel.token.hex()], capture_output=True, text=True,
                                timeout=30)
        assert result.returncode == 0, result.stderr
        assert result.stdout.split() == ["0", "0"], "another user's connection was closed without data or descriptor"
        # The rightful client still gets the channel.
        sock = _connect(channel, channel.token)
        handed, fds, _, _ = socket.recv_fds(sock, 1, 1)
        assert handed == b"\x01" and len(fds) == 1
        os.close(fds[0])
        sock.close()
    finally:
        envs.close()
