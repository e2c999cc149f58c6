"""Evidence that the example learners learn through radserve (issue 5): each check runs the learners
as a user would, reads their metrics.csv, appends a row per run to bench/results/learning.json (the
table docs/learning.md renders: `make docs-tables`), and draws the runs' evaluation curves side by side in docs/learning/<check>.png.

    python bench/learning.py sac-state      # SAC + RAS-S on gym/InvertedPendulum-v5, target >= 900 in 20k steps
    python bench/learning.py rad-sac        # RAD-SAC translate vs pixel SAC on dmc/cartpole-balance, >= 600 in 80k
    python bench/learning.py ppo            # PPO + crop on procgen/bigfish at a reduced budget: the curve rises
    python bench/learning.py dqn-per        # DQN with prioritized 3-step replay vs uniform on CartPole-v1, >= 475 in 50k
    python bench/learning.py drqv2          # DrQ-v2 (server shift, 3-step returns) on cartpole-swingup at the demo's budget, both actor modes: the curves rise
    python bench/learning.py rad-sac --extra --batch-size 512   # extra learner flags, recorded in the table

These are benchmarks, not tests: a run takes minutes to an hour on two cores (`make bench-learning`).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

import record  # bench/record.py: the results file

runs = record.example("runs")  # the examples' run bookkeeping
plot_curves, read_metrics = runs.plot_curves, runs.read_metrics

EXAMPLES = ROOT / "client-py" / "examples"
FIGURES = ROOT / "docs" / "learning"


@dataclass
class Run:
    label: str
    script: str
    flags: "list[str]"


@dataclass
class Check:
    title: str
    runs: "list[Run]"
    metric: str
    target: "float | None"  # None: the check is that the curve rises
    budget: int  # environment steps


CHECKS = {
    "sac-state": Check(
        "SAC-state + RAS-S, gym/InvertedPendulum-v5",
        [Run("SAC + ras_s", "sac_state.py", ["--env", "gym/InvertedPendulum-v5", "--aug", "ras_s",
                                             "--total-steps", "20000", "--eval-every", "2000",
                                             "--learning-starts", "1000", "--torch-threads", "1"])],
        "charts/eval_return", 900.0, 20_000),
    "rad-sac": Check(
        "RAD-SAC translate vs pixel SAC, dmc/cartpole-balance",
        [Run("RAD-SAC translate(108)", "sac_pixels.py", ["--env", "dmc/cartpole-balance", "--aug", "translate(108)"]),
         Run("pixel SAC, no augmentation", "sac_pixels.py", ["--env", "dmc/cartpole-balance", "--aug", "none"])],
        "charts/eval_return", 600.0, 80_000),
    "ppo": Check(
        "PPO + crop, procgen/bigfish (reduced budget)",
        [Run("PPO + crop(56)", "ppo_procgen.py", ["--env", "procgen/bigfish", "--num-envs", "16", "--num-steps", "128",
                                                  "--total-timesteps", "300000", "--eval-every", "20480",
                                                  "--eval-episodes", "16", "--amp", "--torch-threads", "1"])],
        "charts/eval_return", None, 300_000),
    "dqn-per": Check(
        "DQN, prioritized 3-step replay vs uniform, gym/CartPole-v1",
        [Run(label, "dqn_prioritized.py", ["--env", "gym/CartPole-v1", "--total-steps", "50000", "--eval-every", "5000",
                                           "--priority-exponent", exponent])
         for label, exponent in (("prioritized (alpha 0.6)", "0.6"), ("uniform (alpha 0)", "0"))],
        "charts/eval_return", 475.0, 50_000),
    "drqv2": Check(
        "DrQ-v2 shift(4) + 3-step returns, dmc/cartpole-swingup at the demo's budget",
        [Run(f"DrQ-v2, {actor} acts", "drqv2_pixels.py",
             ["--env", "dmc/cartpole-swingup", "--actor", actor, "--image-size", "64", "--num-filters", "16",
              "--hidden-dim", "256", "--batch-size", "32", "--action-repeat", "8", "--update-every", "1",
              "--total-env-steps", "40000", "--num-expl-steps", "250", "--std-steps", "20000", "--lr", "1e-4",
              "--eval-every", "8000", "--eval-episodes", "10", "--render-profile", "fast", "--log-every", "100"])
         for actor in ("learner", "server")],
        "charts/eval_return", None, 40_000),
}

# What the pixel check uses on a CPU-only host (the table records it): the paper's batch of 512
# costs ~2.5 s per update here; bfloat16 convs are 2-4x faster on this CPU (AMX).
CPU_PIXEL_FLAGS = ["--batch-size", "32", "--amp", "--total-env-steps", "80000", "--eval-every", "10000"]


def threshold_step(steps: np.ndarray, values: np.ndarray, target: float) -> "int | None":
    reached = np.flatnonzero(values >= target)
    return int(steps[reached[0]]) if len(reached) else None


def rises(values: np.ndarray) -> bool:
    """The last third of the evaluations is better on average than the first third."""
    third = max(1, len(values) // 3)
    return len(values) >= 3 and values[-third:].mean() > values[:third].mean()


COLUMNS = ["date", "check", "run", "flags", "env steps", "final eval", "best eval", "first step >= target",
           "target met", "wall"]


def append_row(row: "list[str]") -> None:
    """Adds a run's row to bench/results/learning.json, whose table docs/learning.md renders: these runs
    take up to hours each, so the table is a log of runs (each row dated), not one run's figures."""
    path = record.RESULTS / "learning.json"
    rows = json.loads(path.read_text())["tables"][0]["rows"] if path.exists() else []
    rows.append(row)
    record.write("learning", [{"id": "learning", "columns": COLUMNS, "rows": rows, "align": ["l"] * len(COLUMNS),
                               "note": "One row per run, appended by each run (the date column says when it ran; "
                                       "the rows marked GPU ran through bench/gpu on the device named)."}],
                 command="python bench/learning.py CHECK [--extra FLAGS]")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("check", choices=sorted(CHECKS))
    parser.add_argument("--runs-dir", default=str(ROOT / "runs" / "bench"))
    parser.add_argument("--parallel", action=argparse.BooleanOptionalAction, default=True,
                        help="run a check's learners at the same time (one torch thread each)")
    parser.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="flags passed to every learner")
    options = parser.parse_args()
    check = CHECKS[options.check]
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    started = []
    for index, run in enumerate(check.runs):
        flags = list(run.flags)
        if run.script == "sac_pixels.py":
            flags += CPU_PIXEL_FLAGS
        flags += options.extra
        if options.parallel and len(check.runs) > 1:
            flags += ["--torch-threads", "1"]
        runs_dir = Path(options.runs_dir) / f"{options.check}-{stamp}-{index}"
        command = [sys.executable, str(EXAMPLES / run.script), *flags, "--runs-dir", str(runs_dir)]
        print("running:", " ".join(command), flush=True)
        process = subprocess.Popen(command, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        started.append((run, flags, runs_dir, process, time.perf_counter()))
        if not options.parallel:
            process.wait()
    curves = {}
    for run, flags, runs_dir, process, start in started:
        code = process.wait()
        wall = time.perf_counter() - start
        if code != 0:
            sys.exit(f"{run.script} failed with exit code {code}")
        run_dir = next(runs_dir.iterdir())
        curves[run.label] = run_dir
        steps, values = read_metrics(run_dir)[check.metric]
        if check.target is None:
            reached, met = "-", "rises" if rises(values) else "does not rise"
        else:
            first = threshold_step(steps, values, check.target)
            reached, met = (str(first) if first is not None else "never"), ("yes" if first is not None else "no")
        row = [datetime.date.today().isoformat(), check.title, run.label, "`" + " ".join(flags) + "`", str(int(steps[-1])),
               f"{values[-1]:.1f}", f"{values.max():.1f}", reached, met, f"{wall / 60:.0f} min"]
        append_row(row)
        print(" | ".join(row))
    FIGURES.mkdir(parents=True, exist_ok=True)
    figure = plot_curves(curves, FIGURES / f"{options.check}.png", title=check.title)
    print(f"curves: {figure}")


if __name__ == "__main__":
    main()
