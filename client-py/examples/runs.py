"""The bookkeeping of an example learner's run, kept out of the algorithm files (CleanRL keeps the
same things beside tyro and SummaryWriter): a run directory with its arguments, metrics in CSV and
TensorBoard, learning-curve plots, the device and the run's name. It lives beside the examples (a
learner copied out of client-py/examples/ takes this file with it); what learners share beyond a run
(evaluation, the servers' actors followed, the loop while the servers act) is `radserve.training`.
Command lines come from each learner's `Args` dataclass through tyro (`tyro.cli(Args)`).

TensorBoard and matplotlib come with the learners' extra (`make torch`); they are imported when used.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import time
from pathlib import Path

import numpy as np


def select_device(name: str):
    """`auto`: the first CUDA device when there is one, else the CPU."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class RunLog:
    """A run directory: `args.json`, `metrics.csv` (step, wall time, name, value), TensorBoard events,
    `checkpoint.pt` at each evaluation, and at the end `curve.png` and `summary.txt`."""

    def __init__(self, root: "str | Path", name: str, args) -> None:
        self.dir = Path(root) / name
        self.dir.mkdir(parents=True, exist_ok=True)
        (self.dir / "args.json").write_text(json.dumps(dataclasses.asdict(args), indent=2) + "\n")
        self._csv_file = open(self.dir / "metrics.csv", "w", newline="")
        self._csv = csv.writer(self._csv_file)
        self._csv.writerow(["step", "wall_time", "name", "value"])
        from torch.utils.tensorboard import SummaryWriter

        self._writer = SummaryWriter(str(self.dir))
        self._writer.add_text("args", "\n".join(f"{k}: {v}" for k, v in dataclasses.asdict(args).items()))
        self._start = time.time()
        self.started = time.perf_counter()
        # (step, mean return) of every evaluation, in order.
        self.evaluations: "list[tuple[int, float]]" = []

    def scalar(self, name: str, value: float, step: int) -> None:
        value = float(value)
        self._csv.writerow([step, f"{time.time() - self._start:.3f}", name, repr(value)])
        self._writer.add_scalar(name, value, step)

    def scalars(self, step: int, **named: float) -> None:
        """`scalars(step, **{"losses/qf_loss": 0.3})`."""
        for name, value in named.items():
            self.scalar(name, value, step)

    def evaluation(self, step: int, returns: "list[float]", checkpoint: "dict | None" = None) -> float:
        """Logs an evaluation's returns (charts/eval_return and its std), keeps (step, mean), and saves
        `checkpoint` (a learner's state) to checkpoint.pt when given; the mean."""
        mean = float(np.mean(returns))
        self.evaluations.append((step, mean))
        self.scalars(step, **{"charts/eval_return": np.mean(returns), "charts/eval_return_std": np.std(returns)})
        self.flush()
        if checkpoint is not None:
            import torch

            torch.save(checkpoint, self.dir / "checkpoint.pt")
        return mean

    def summarize(self, env_id: str, label: str, title: str, episodes: int, started: float) -> str:
        """Draws curve.png and writes (and prints) the run's one line, which `make demo` ends with:
        the first and last evaluation, the best, the minutes since `started`, the curve's path."""
        curve = plot_curves({label: self.dir}, self.dir / "curve.png", title=title)
        (first_steps, first), (last_steps, last) = self.evaluations[0], self.evaluations[-1]
        best = max(value for _, value in self.evaluations)
        summary = (f"{env_id}: evaluation return {first:.1f} at {first_steps} -> {last:.1f} at {last_steps} environment "
                   f"steps (best {best:.1f}, {episodes} episodes each, {(time.perf_counter() - started) / 60:.1f} min); "
                   f"curve: {curve}")
        (self.dir / "summary.txt").write_text(summary + "\n")
        print(summary)
        return summary

    def flush(self) -> None:
        self._csv_file.flush()
        self._writer.flush()

    def close(self) -> None:
        self._csv_file.close()
        self._writer.close()


def read_metrics(run_dir: "str | Path") -> "dict[str, tuple[np.ndarray, np.ndarray]]":
    """metrics.csv of a run as {name: (steps, values)}."""
    series: "dict[str, tuple[list, list]]" = {}
    with open(Path(run_dir) / "metrics.csv", newline="") as handle:
        for row in csv.DictReader(handle):
            steps, values = series.setdefault(row["name"], ([], []))
            steps.append(int(row["step"]))
            values.append(float(row["value"]))
    return {name: (np.array(steps), np.array(values)) for name, (steps, values) in series.items()}


def binned_mean(steps: np.ndarray, values: np.ndarray, bins: int = 40) -> "tuple[np.ndarray, np.ndarray]":
    """Means of `values` over equal-width bins of `steps`, each placed at the mean step of its bin.

    Training episodes arrive by the thousand and each is noisy (a ProcGen return is a small integer);
    the binned mean is the readable training curve. Empty bins are dropped."""
    steps = np.asarray(steps, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if steps.size == 0:
        return steps, values
    edges = np.linspace(steps.min(), steps.max(), bins + 1)
    which = np.clip(np.searchsorted(edges, steps, side="right") - 1, 0, bins - 1)
    counts = np.bincount(which, minlength=bins)
    kept = counts > 0
    centres = np.bincount(which, weights=steps, minlength=bins)[kept] / counts[kept]
    means = np.bincount(which, weights=values, minlength=bins)[kept] / counts[kept]
    return centres, means


def plot_curves(runs: "dict[str, str | Path]", out: "str | Path", *, title: str = "",
                metric: str = "charts/eval_return", spread: str = "charts/eval_return_std",
                train_metric: "str | None" = "charts/episodic_return",
                xlabel: str = "environment steps") -> Path:
    """Learning curves of labelled runs in a PNG: the mean evaluation return (its spread shaded) and,
    beside it when the runs logged training episodes, their return as a binned mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = {label: read_metrics(run_dir) for label, run_dir in runs.items()}
    with_train = train_metric is not None and any(train_metric in m for m in metrics.values())
    figure, panels = plt.subplots(1, 2 if with_train else 1, figsize=(11.0 if with_train else 6.4, 4.0),
                                  dpi=120, squeeze=False)
    evaluation = panels[0][0]
    for label, series in metrics.items():
        if metric not in series:
            continue
        steps, values = series[metric]
        line, = evaluation.plot(steps, values, marker="o", markersize=3, label=label)
        if spread in series and len(series[spread][1]) == len(values):
            deviation = series[spread][1]
            evaluation.fill_between(steps, values - deviation, values + deviation, color=line.get_color(), alpha=0.2)
    evaluation.set_ylabel(metric.split("/")[-1].replace("_", " "))
    axes_used = [evaluation]
    if with_train:
        training = panels[0][1]
        for label, series in metrics.items():
            if train_metric in series:
                training.plot(*binned_mean(*series[train_metric]), label=label)
        training.set_ylabel("training episode return (binned mean)")
        axes_used.append(training)
    for axes in axes_used:
        axes.set_xlabel(xlabel)
        axes.grid(alpha=0.3)
        if len(runs) > 1:
            axes.legend()
    figure.suptitle(title)
    figure.tight_layout()
    out = Path(out)
    figure.savefig(out)
    plt.close(figure)
    return out


def run_name(env_id: str, algorithm: str, seed: int) -> str:
    """CleanRL's run naming: env__algorithm__seed__unixtime (`/` in env ids becomes `-`)."""
    return f"{env_id.replace('/', '-')}__{algorithm}__{seed}__{int(time.time())}"
