"""Does RAD-SAC learn as well when the servers act? `make demo`'s task (RAD-SAC translate(72) on
dm_control cartpole-swingup from 64x64 pixels, 40k environment steps, batch 32) run with
`--actor learner` (this side steps the envs over gRPC and runs the actor) and `--actor server` (the
actor is exported to ONNX every `--policy-every` updates; the server steps the envs with it, records
each transition's policy version, and the rate limiter keeps one update of a batch per transition
acted), over the same seeds. For each evaluation point (10 episodes each, on the servers for
`--actor server`) it writes the mean and sample standard deviation over the seeds of both, whether the
server-side mean is within one learner-side standard deviation of the learner-side mean or above it,
the server-side runs' mean policy staleness, and the wall time; the table is
bench/results/actor_learning.json (docs/actors.md renders it), the curves docs/learning/actors.png.

    python bench/actor_learning.py [--seeds 1,2,3] [--parallel 2] [--extra FLAGS...]
    python bench/actor_learning.py --tabulate 20261206-194040   # the table again from those runs

A run takes about six minutes alone on two cores; `--parallel 2` runs a learner-side and a
server-side run of one seed at the same time (one torch thread each), so both see the same load.
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

import record

read_metrics = record.example("runs").read_metrics  # the examples' run bookkeeping

EXAMPLE = ROOT / "client-py" / "examples" / "sac_pixels.py"
FIGURE = ROOT / "docs" / "learning" / "actors.png"
# make demo's learner (the Makefile's DEMO_FLAGS); the seed, the actor and the thread count are added per run.
DEMO_FLAGS = ["--env", "dmc/cartpole-swingup", "--image-size", "64", "--aug", "translate(72)", "--num-filters", "16",
              "--total-env-steps", "40000", "--init-steps", "125", "--batch-size", "32", "--eval-every", "8000",
              "--eval-episodes", "10", "--render-profile", "fast", "--log-every", "50"]
ACTORS = ("learner", "server")


def evaluations(run_dir: Path, eval_every: int) -> "dict[int, tuple[int, float]]":
    """A run's evaluations keyed by the evaluation point they belong to (a multiple of eval_every):
    server-side runs evaluate when the acted count has passed the point, a few env steps after it."""
    steps, values = read_metrics(run_dir)["charts/eval_return"]
    return {int(round(step / eval_every)) * eval_every: (int(step), float(value)) for step, value in zip(steps, values)}


def wall_minutes(run_dir: Path) -> float:
    """From the run directory's creation (args.json) to the learner's summary (summary.txt)."""
    return ((run_dir / "summary.txt").stat().st_mtime - (run_dir / "args.json").stat().st_mtime) / 60


def staleness(run_dir: Path) -> float:
    series = read_metrics(run_dir).get("charts/policy_staleness")
    return float(np.mean(series[1])) if series is not None and len(series[1]) else float("nan")


def plot(curves: "dict[str, dict[int, list[float]]]", out: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(6.4, 4.0), dpi=120)
    for label, points in curves.items():
        steps = np.array(sorted(points))
        means = np.array([np.mean(points[s]) for s in steps])
        stds = np.array([np.std(points[s], ddof=1) if len(points[s]) > 1 else 0.0 for s in steps])
        line, = axes.plot(steps, means, marker="o", markersize=3, label=label)
        axes.fill_between(steps, means - stds, means + stds, color=line.get_color(), alpha=0.2)
    axes.set_xlabel("environment steps")
    axes.set_ylabel("evaluation return (mean over seeds, +-1 std)")
    axes.grid(alpha=0.3)
    axes.legend()
    axes.set_title(title)
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out)
    plt.close(figure)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="1,2,3")
    parser.add_argument("--parallel", type=int, default=2, choices=(1, 2), help="runs at a time (2: one seed's pair)")
    parser.add_argument("--runs-dir", default=str(ROOT / "runs" / "bench" / "actor-learning"))
    parser.add_argument("--tabulate", metavar="STAMP", help="no runs: tabulate those of an earlier invocation")
    parser.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="flags passed to every run")
    options = parser.parse_args()
    seeds = [int(s) for s in options.seeds.split(",")]
    runs_dir = Path(options.runs_dir)
    extra = (["--torch-threads", "1"] if options.parallel > 1 else []) + options.extra
    stamp = options.tabulate or time.strftime("%Y%m%d-%H%M%S")
    if not options.tabulate:
        run_all(runs_dir, stamp, seeds, extra, options.parallel)
    # What made the runs (a --tabulate invocation only reads them back).
    command = shlex.join([".venv/bin/python", "bench/actor_learning.py", "--seeds", options.seeds, "--parallel",
                          str(options.parallel), *(["--extra", *options.extra] if options.extra else [])])
    if options.tabulate:
        command += f" (runs {stamp}; this table read back with --tabulate)"
    tabulate(runs_dir, stamp, seeds, extra, options.parallel, command)


def run_all(runs_dir: Path, stamp: str, seeds: "list[int]", extra: "list[str]", parallel: int) -> None:
    """Every (seed, actor) run, `parallel` at a time; each one's output in runs_dir/STAMP-ACTOR-SEED.log."""
    runs_dir.mkdir(parents=True, exist_ok=True)
    jobs = [(seed, actor) for seed in seeds for actor in ACTORS]
    for first in range(0, len(jobs), parallel):
        running = []
        for seed, actor in jobs[first:first + parallel]:
            name = f"{stamp}-{actor}-{seed}"
            command = [sys.executable, str(EXAMPLE), *DEMO_FLAGS, "--seed", str(seed), "--actor", actor, *extra,
                       "--runs-dir", str(runs_dir / name)]
            print("running:", " ".join(command), flush=True)
            log = open(runs_dir / f"{name}.log", "w")
            process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                       env={**os.environ, "PYTHONUNBUFFERED": "1"})
            running.append((seed, actor, process, log))
        for seed, actor, process, log in running:
            code = process.wait()
            log.close()
            if code != 0:
                sys.exit(f"seed {seed}, --actor {actor} failed with exit code {code}: {log.name}")
            run_dir = next((runs_dir / f"{stamp}-{actor}-{seed}").iterdir())
            print(f"seed {seed}, --actor {actor}: {wall_minutes(run_dir):.1f} min", flush=True)


def tabulate(runs_dir: Path, stamp: str, seeds: "list[int]", extra: "list[str]", parallel: int, command: str) -> None:
    eval_every = int(DEMO_FLAGS[DEMO_FLAGS.index("--eval-every") + 1])
    results = {(seed, actor): next((runs_dir / f"{stamp}-{actor}-{seed}").iterdir()) for seed in seeds for actor in ACTORS}
    points: "dict[str, dict[int, list[float]]]" = {actor: {} for actor in ACTORS}
    reached: "dict[str, dict[int, list[int]]]" = {actor: {} for actor in ACTORS}
    for (seed, actor), run_dir in results.items():
        for point, (step, value) in evaluations(run_dir, eval_every).items():
            points[actor].setdefault(point, []).append(value)
            reached[actor].setdefault(point, []).append(step)
    rows = []
    for point in sorted(set(points["learner"]) & set(points["server"])):
        learner, server = np.array(points["learner"][point]), np.array(points["server"][point])
        spread = float(np.std(learner, ddof=1)) if len(learner) > 1 else 0.0
        within = "yes" if server.mean() >= learner.mean() - spread else "no"
        steps = reached["server"][point]
        rows.append([f"{point:,}", record.cell(float(learner.mean()), digits=1), record.cell(spread, digits=1),
                     record.cell(float(server.mean()), digits=1),
                     record.cell(float(np.std(server, ddof=1)) if len(server) > 1 else 0.0, digits=1),
                     f"{min(steps):,}-{max(steps):,}" if min(steps) != max(steps) else f"{steps[0]:,}", within])
        print(record.plain(rows[-1]))
    walls = {actor: [wall_minutes(results[seed, actor]) for seed in seeds] for actor in ACTORS}
    finals = {actor: [evaluations(results[seed, actor], eval_every)[max(points[actor])][1] for seed in seeds]
              for actor in ACTORS}
    per_seed = [[f"--actor {actor}", ", ".join(f"{value:.1f}" for value in finals[actor]),
                 record.ranged(walls[actor], digits=1, suffix=" min"),
                 record.cell(float(np.nanmean([staleness(results[seed, actor]) for seed in seeds])), digits=1)
                 if actor == "server" else "-"] for actor in ACTORS]
    settings = {"seeds": seeds, "parallel": parallel, "flags": DEMO_FLAGS + extra, "runs": stamp}
    record.write("actor_learning", [
        {"id": "actor_learning", "columns": ["env steps", "learner-side mean", "std", "server-side mean", "std",
                                             "server-side evaluated at", "server-side within one std or above"],
         "rows": rows, "align": ["r", "r", "r", "r", "r", "r", "l"],
         "note": f"Seeds {', '.join(map(str, seeds))}; evaluation return over 10 episodes per seed; std is the sample "
                 "standard deviation over the seeds."},
        {"id": "actor_learning_runs", "columns": ["run", "final return per seed", "wall per run",
                                                  "mean age of a sampled transition's policy (versions)"],
         "rows": per_seed, "align": ["l", "r", "r", "r"]},
    ], settings=settings, command=command)
    print(f"curves: {plot(points, FIGURE, 'RAD-SAC translate(72), dmc/cartpole-swingup: who acts')}")


if __name__ == "__main__":
    main()
