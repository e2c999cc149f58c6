"""SIGTERM drains: NOT_SERVING at once, new sessions refused, open streams ended with a status, exit
within the drain deadline with no worker left; a second signal exits at once."""

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

import radserve
from _procs import wait_serving, worker_pids
from radserve.server import find_binary


def _running(pid):
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state not in ("Z", "X")


def _health(address):
    with grpc.insecure_channel(address) as channel:
        reply = health_pb2_grpc.HealthStub(channel).Check(
            health_pb2.HealthCheckRequest(service="radserve.v1.RadServe"), timeout=5)
        return reply.status


def _healthcheck(address, *args):
    """`radserve healthcheck`, as a container HEALTHCHECK runs it."""
    return subprocess.run([find_binary(), "healthcheck", "--address", address, *args], capture_output=True, text=True,
                          timeout=30)


def _busy_server(notice, drain):
    server = radserve.LocalServer(workers=2, env={
        "RADSERVE__SERVER__SHUTDOWN_NOTICE_S": str(notice), "RADSERVE__SERVER__DRAIN_TIMEOUT_S": str(drain)})
    server.start()
    client = radserve.Client(server.address)
    envs = client.make_vec("gym/CartPole-v1", num_envs=2, replay_capacity=1000)
    envs.reset(seed=0)
    for _ in range(20):
        envs.step(np.zeros(2, dtype=np.int64))
    # SERVING (the catalog built) before the stream opens: a stream left unread for the tens of
    # seconds that takes would fill the client's buffers, and a client that does not read within a
    # second of the shutdown misses the stream's status (docs/operations.md, Shutdown).
    with grpc.insecure_channel(server.address) as channel:
        wait_serving(channel, "radserve.v1.RadServe")
    stream = envs.sample_batches(batch_size=4)
    next(iter(stream))
    return server, client, envs, stream


def _wait_forworker_pids(pid, count=2, timeout=60):
    deadline = time.monotonic() + timeout
    while len(worker_pids(pid)) < count:
        assert time.monotonic() < deadline, "workers did not start"
        time.sleep(0.1)
    return worker_pids(pid)


def test_sigterm_drains_with_statuses_and_exits_within_the_deadline():
    server, client, envs, stream = _busy_server(notice=2.0, drain=10.0)
    try:
        workers = _wait_forworker_pids(server.process.pid)
        for service in ("", "radserve.v1.RadServe", "dm_env_rpc.v1.Environment"):
            checked = _healthcheck(server.address, "--service", service)
            assert (checked.returncode, checked.stdout) == (0, "SERVING\n"), checked.stderr
        started = time.monotonic()
        server.process.send_signal(signal.SIGTERM)
        time.sleep(0.3)
        # During the notice: still answering, but not serving and refusing new sessions.
        assert _health(server.address) == health_pb2.HealthCheckResponse.NOT_SERVING
        checked = _healthcheck(server.address)
        assert (checked.returncode, checked.stdout) == (1, "NOT_SERVING\n")
        assert "reports NOT_SERVING" in checked.stderr
        with pytest.raises(radserve.UnavailableError, match="shutting down"):
            client.make_vec("gym/CartPole-v1")
        # The open stream ends with a status, not silently and not never.
        with pytest.raises(radserve.UnavailableError, match="shutting down"):
            for _ in stream:
                pass
        code = server.process.wait(timeout=15)
        elapsed = time.monotonic() - started
        assert code == 0
        assert elapsed < 10.0, f"exit took {elapsed:.1f} s, past the drain deadline"
        assert not [pid for pid in workers if _running(pid)], "a worker outlived the server"
    finally:
        client.close()
        server.stop()


def test_healthcheck_fails_clearly_without_a_server():
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    checked = _healthcheck(f"127.0.0.1:{port}", "--timeout-s", "2")
    assert checked.returncode == 1 and checked.stdout == ""
    assert f"connecting to 127.0.0.1:{port}" in checked.stderr


def test_a_second_signal_exits_at_once():
    # A long notice and drain: only the second signal can make it exit quickly.
    server, client, envs, stream = _busy_server(notice=60.0, drain=120.0)
    try:
        workers = _wait_forworker_pids(server.process.pid)
        server.process.send_signal(signal.SIGTERM)
        time.sleep(0.5)
        assert server.process.poll() is None, "still draining after the first signal"
        started = time.monotonic()
        server.process.send_signal(signal.SIGINT)
        code = server.process.wait(timeout=10)
        assert time.monotonic() - started < 5
        assert code != 0
        deadline = time.monotonic() + 5
        while [pid for pid in workers if _running(pid)] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [pid for pid in workers if _running(pid)], "a worker outlived the server"
    finally:
        stream.close()
        client.close()
        server.stop()


def test_a_server_whose_launcher_already_died_exits_at_once():
    # (A launcher killed later takes its server along: client-py/tests/test_client.py.)
    binary = radserve.server.find_binary()
    # Our pid is not the server's parent's (a shell in between): as if the launcher had died.
    shell = subprocess.run(["sh", "-c", f'"{binary}" serve --address 127.0.0.1:0 --workers 1; echo status $?'],
                           env={**os.environ, "RADSERVE_PARENT_PID": str(os.getpid())},
                           capture_output=True, text=True, timeout=30)
    assert "status 1" in shell.stdout, shell
    assert "has already exited" in shell.stderr, shell.stderr
