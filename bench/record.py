"""Results files of the benchmarks: each bench script writes `bench/results/<name>.json` through
`record.write` (what ran, on which machine, at which commit, and its tables as figures with their
ranges), and `scripts/docs_tables.py` (`make docs-tables`) renders every table into the README and
docs/ where a `<!-- BEGIN table:<id> -->` marker asks for it. Nothing in the docs is typed by hand.

A table is {"id", "columns", "rows", "align"?, "note"?}; a cell is a string, a number, or
{"value", "low"?, "high"?, "digits"?, "suffix"?}: a median and the range of the rounds it came from.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"


def _support():
    """tests/_procs.py, the tests' support, loaded from its file (it loads the rest the same way)."""
    import importlib.util

    if "_procs" not in sys.modules:
        spec = importlib.util.spec_from_file_location("_procs", ROOT / "tests" / "_procs.py")
        sys.modules["_procs"] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules["_procs"])
    return sys.modules["_procs"]


def load(path: Path, name: str, package: bool = False):
    """The module (or package) at `path` under `name`: a benchmark's way to what is not installed
    (the tests' helpers, the examples' runs.py, the worker's package, another client's checkout),
    without editing sys.path."""
    return _support().load(path, name, package)


def tests_helper(name: str):
    """tests/<name>.py (policies, k8s_harness, _procs)."""
    return load(ROOT / "tests" / f"{name}.py", name)


def example(name: str):
    """client-py/examples/<name>.py (runs: the examples' run bookkeeping)."""
    return _support().example(name)


def worker_module(name: str = "adapters"):
    """A module of the worker's package (server/sim/python/radserve_worker), the one the worker embeds."""
    return _support().worker_module(name)


def machine() -> dict:
    """The machine a run was made on, as a reader compares figures between runs."""
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory_gib = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return {"cpu": cpu, "cores": os.cpu_count(), "memory_gib": round(memory_gib, 1),
            "os": platform.platform(terse=True), "python": platform.python_version()}


def commit() -> str:
    """The commit the run measured, with `+changes` when the tree differed from it."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True).stdout.strip()
        return head + ("+changes" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def cell(value: float, low: "float | None" = None, high: "float | None" = None, digits: int = 0,
         suffix: str = "") -> dict:
    """A figure with the range it came from (low/high of the rounds), shown with `digits` decimals."""
    out = {"value": value, "digits": digits}
    if low is not None and high is not None:
        out["low"], out["high"] = low, high
    if suffix:
        out["suffix"] = suffix
    return out


def ranged(values, digits: int = 0, suffix: str = "") -> dict:
    """The median of `values` with their range (none for a single value)."""
    values = list(values)
    low, high = (min(values), max(values)) if len(values) > 1 else (None, None)
    return cell(statistics.median(values), low, high, digits, suffix)


def plain(row: list) -> str:
    """A table row as one line of plain text (the figures without their ranges), for the terminal."""
    def text(cell) -> str:
        if isinstance(cell, dict):
            return f"{cell['value']:,.{cell.get('digits', 0)}f}{cell.get('suffix', '')}"
        return str(cell)

    return " | ".join(text(cell) for cell in row)


def write(name: str, tables: "list[dict]", settings: "dict | None" = None, path: "Path | None" = None,
          command: "str | None" = None) -> Path:
    """Writes the results file of bench `name`: the command that ran (this script's command line unless
    given), settings, machine, commit, tables."""
    path = path or RESULTS / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    command = command or shlex.join([".venv/bin/python", os.path.relpath(sys.argv[0], ROOT), *sys.argv[1:]])
    document = {
        "bench": name,
        "command": command,
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "commit": commit(),
        "machine": machine(),
        "settings": settings or {},
        "tables": tables,
    }
    path.write_text(json.dumps(document, indent=1) + "\n")
    print(f"results: {os.path.relpath(path, ROOT)}")
    return path
