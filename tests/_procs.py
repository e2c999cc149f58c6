"""Process helpers for the tests that signal a server's workers, and waiting for a server's health."""

import os
import signal
import time
from contextlib import contextmanager
from pathlib import Path

from grpc_health.v1 import health_pb2, health_pb2_grpc


def _read(path: Path) -> bytes:
    """A /proc file, or nothing when its process or thread has gone meanwhile."""
    try:
        return path.read_bytes()
    except (FileNotFoundError, ProcessLookupError):
        return b""


def worker_pids(server_pid):
    """The server's worker processes (pool and transient), sorted. Workers are spawned from tokio's
    threads: each thread (task) lists its own children. A transient worker (the catalog's) is killed
    once it answered, so one may leave while it is listed: it is left out."""
    children = {int(pid) for task in Path(f"/proc/{server_pid}/task").iterdir()
                for pid in _read(task / "children").split()}
    return sorted(pid for pid in children if b"\0worker\0" in _read(Path(f"/proc/{pid}/cmdline")))


@contextmanager
def stopped(pid):
    """SIGSTOP `pid` for the block; SIGCONT after, if the process still exists."""
    os.kill(pid, signal.SIGSTOP)
    try:
        yield
    finally:
        try:
            os.kill(pid, signal.SIGCONT)
        except ProcessLookupError:
            pass


def wait_serving(channel, service: str = "", timeout: float = 300) -> None:
    """Asks grpc.health.v1 about `service` over `channel` until it answers SERVING: a server is
    NOT_SERVING until its catalog is built, tens of seconds after it starts."""
    stub = health_pb2_grpc.HealthStub(channel)
    deadline = time.monotonic() + timeout
    while stub.Check(health_pb2.HealthCheckRequest(service=service), timeout=10).status \
            != health_pb2.HealthCheckResponse.SERVING:
        assert time.monotonic() < deadline, f"{service or 'the server'} not SERVING within {timeout} s"
        time.sleep(0.2)
