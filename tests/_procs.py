"""Process helpers for the tests that signal a server's workers."""

import os
import signal
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
