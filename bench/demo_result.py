"""Records a `make demo` run (`make bench-demo` runs the demo, then this): the evaluation returns
against environment steps and the wall time, from the run's own metrics.csv, into
bench/results/demo.json, which the README renders (`make docs-tables`).

    .venv/bin/python bench/demo_result.py runs/demo/<run>/
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import record  # noqa: E402  (bench/record.py: the results file)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="the run directory make demo wrote (runs/demo/<run>/)")
    args = parser.parse_args()
    evaluations, wall_s = [], 0.0
    with open(args.run / "metrics.csv", newline="") as handle:
        for row in csv.DictReader(handle):
            wall_s = max(wall_s, float(row["wall_time"]))
            if row["name"] == "charts/eval_return":
                evaluations.append((int(row["step"]), float(row["value"])))
    if not evaluations:
        raise SystemExit(f"{args.run}/metrics.csv has no charts/eval_return: not a finished run")
    flags = json.loads((args.run / "args.json").read_text())
    returns = ", ".join(f"{value:.1f}" for _, value in evaluations[1:-1])
    (first_step, first), (last_step, last) = evaluations[0], evaluations[-1]
    table = {
        "id": "demo",
        "columns": [f"`make demo`'s learner", f"evaluation return at {first_step // 1000}k -> {last_step // 1000}k "
                    f"env steps ({flags['eval_episodes']} episodes each)", "returns in between", "wall"],
        "rows": [[f"RAD-SAC {flags['aug']}, {flags['num_filters']} filters, {flags['image_size']}x{flags['image_size']}, "
                  f"batch {flags['batch_size']}", f"{first:.1f} -> {last:.1f}", returns, f"{wall_s / 60:.1f} min"]],
        "note": "Set-up done before the run (the first `make demo` on a fresh clone also installs .venv and builds "
                "the server).",
    }
    record.write("demo", [table], {"run": str(args.run), "flags": flags}, command="make bench-demo")


if __name__ == "__main__":
    main()
