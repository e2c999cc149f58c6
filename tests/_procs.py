"""Process helpers for the tests that signal a server's workers."""

import os
import signal
from contextlib import contextmanager
from pathlib import Path


def worker_pids(server_pid):
    """The server's worker processes (pool and transient), sorted. Workers are spawned from tokio's
    threads: each thread (task) lists its own children."""
    children = {int(pid) for task in Path(f"/proc/{server_pid}/task").iterdir()
                for pid in (task / "children").read_text().split()}
    return sorted(pid for pid in children if b"\0worker\0" in Path(f"/proc/{pid}/cmdline").read_bytes())


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
