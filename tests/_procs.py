"""The tests' support: process helpers for the tests that signal a server's workers, waiting for a
server's health, and loading what is neither installed nor beside the tests (the examples, scripts/,
the worker's package) from its files. Benchmarks reach the same through bench/record.py."""

import os
import signal
import time
from contextlib import contextmanager
from pathlib import Path


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
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    stub = health_pb2_grpc.HealthStub(channel)
    deadline = time.monotonic() + timeout
    while stub.Check(health_pb2.HealthCheckRequest(service=service), timeout=10).status \
            != health_pb2.HealthCheckResponse.SERVING:
        assert time.monotonic() < deadline, f"{service or 'the server'} not SERVING within {timeout} s"
        time.sleep(0.2)


_ROOT = Path(__file__).resolve().parents[1]


def load(path: Path, name: str, package: bool = False):
    """The module (or, `package`, the package) at `path`, loaded from its file under `name`, once:
    what is neither installed nor beside the tests (the examples, scripts/, the worker's package)
    is reached this way, and nothing here edits sys.path."""
    import importlib.util
    import sys

    if name in sys.modules:
        return sys.modules[name]
    if package:
        spec = importlib.util.spec_from_file_location(name, path / "__init__.py", submodule_search_locations=[str(path)])
    else:
        spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # the examples import `runs` by name: it must be this module
    spec.loader.exec_module(module)
    return module


def worker_module(name: str):
    """A module of the worker's package (server/sim/python/radserve_worker), the one the worker embeds."""
    import importlib

    load(_ROOT / "server" / "sim" / "python" / "radserve_worker", "radserve_worker", package=True)
    return importlib.import_module(f"radserve_worker.{name}")


def script(name: str):
    """scripts/<name>.py (docs_tables)."""
    return load(_ROOT / "scripts" / f"{name}.py", name)


def example(name: str):
    """An example program's module (client-py/examples/<name>.py), loaded from its file: the
    examples are files a learner copies, not a package."""
    return load(_ROOT / "client-py" / "examples" / f"{name}.py", name)
