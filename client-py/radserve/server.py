"""Starting a radserve server on this machine, for scripts, examples and tests."""

import os
import shutil
import signal
import subprocess
import sysconfig
import threading
from pathlib import Path

def find_binary() -> str:
    """$RADSERVE_BIN; else the release build of the repository this package lives in (a clone, after
    `make setup`); else the one the `radserve-server` wheel installed beside this interpreter (a
    virtualenv used without activating it); else `radserve` on PATH."""
    explicit = os.environ.get("RADSERVE_BIN")
    if explicit:
        return explicit
    for parent in Path(__file__).resolve().parents:
        candidate = parent / "target" / "release" / "radserve"
        if candidate.exists():
            return str(candidate)
    installed = Path(sysconfig.get_path("scripts")) / "radserve"
    if installed.is_file() and os.access(installed, os.X_OK):
        return str(installed)
    found = shutil.which("radserve")
    if found:
        return found
    raise FileNotFoundError(
        "no radserve binary: `pip install radserve-server` (or `pip install \"radserve[server]\"`) into this "
        "environment, run `make setup` in a clone, or set RADSERVE_BIN")


class LocalServer:
    """A `radserve serve` child process on a free localhost port. It is stopped when the thread that
    started it ends, cleanup or not: the server asks the kernel for SIGTERM when its parent dies
    (`RADSERVE_PARENT_PID`, PR_SET_PDEATHSIG), so a learner killed without cleanup leaves no server
    behind. Start it from the main thread.

    >>> with LocalServer(workers=2) as server:
    ...     client = radserve.Client(server.address)
    """

    def __init__(self, *, workers: "int | None" = None, address: str = "127.0.0.1:0", binary: "str | None" = None,
                 env: "dict | None" = None, startup_timeout: float = 60.0):
        self.binary = binary or find_binary()
        self.args = [self.binary, "serve", "--address", address]
        if workers is not None:
            self.args += ["--workers", str(workers)]
        self.env = {**os.environ, **(env or {}), "RADSERVE_PARENT_PID": str(os.getpid())}
        self.startup_timeout = startup_timeout
        self.process: "subprocess.Popen | None" = None
        self.address: "str | None" = None

    def start(self) -> str:
        # No preexec_fn: code run between fork and exec in a process with threads (grpcio's) can
        # deadlock the child before it starts.
        self.process = subprocess.Popen(self.args, stdout=subprocess.PIPE, env=self.env, text=True)
        found: dict = {}

        def read_address():
            for line in self.process.stdout:
                if line.startswith("radserve listening on "):
                    found["address"] = line.split()[-1]
                    return

        reader = threading.Thread(target=read_address, daemon=True)
        reader.start()
        reader.join(self.startup_timeout)
        if "address" not in found:
            # The reader ends early only when the server closed its stdout: it is exiting.
            code = None if reader.is_alive() else self._wait_quietly(5)
            self.stop()
            if code is not None:
                raise RuntimeError(f"radserve exited with status {code} before it was listening (its stderr says why)")
            raise RuntimeError(f"radserve did not report its address within {self.startup_timeout} s")
        self.address = found["address"]
        return self.address

    def _wait_quietly(self, timeout: float) -> "int | None":
        try:
            return self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, timeout: float = 20.0) -> "int | None":
        if self.process is None or self.process.poll() is not None:
            return None if self.process is None else self.process.returncode
        self.process.send_signal(signal.SIGTERM)
        try:
            return self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            return self.process.wait()

    def __enter__(self) -> "LocalServer":
        self.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self.stop()
