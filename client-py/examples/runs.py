"""The bookkeeping every example learner shares, kept out of the algorithm files (CleanRL keeps the
same things in tyro and SummaryWriter): a command line built from an `Args` dataclass and its field
docstrings, a run directory with metrics in CSV and TensorBoard, evaluation episodes on a session, the
evaluation view that matches an augmentation pipeline, and learning-curve plots. It lives beside the
examples (a learner copied out of client-py/examples/ takes this file with it), not in the package.

TensorBoard and matplotlib come with the learners' extra (`make torch`); they are imported when used.
"""

from __future__ import annotations

import argparse
import ast
import csv
import dataclasses
import inspect
import json
import math
import re
import textwrap
import time
from pathlib import Path
from typing import Callable, Iterable

import numpy as np


def field_docs(cls) -> "dict[str, str]":
    """The docstring under each field of a dataclass (the string literal on the line after it)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body
    docs = {}
    for statement, following in zip(body, body[1:]):
        if (isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name)
                and isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)
                and isinstance(following.value.value, str)):
            docs[statement.target.id] = " ".join(following.value.value.split())
    return docs


def parse_args(cls, description: "str | None" = None, argv: "list[str] | None" = None):
    """An instance of the dataclass `cls` from the command line: one `--field-name` per field, typed
    by its default, documented by its docstring; booleans take `--name/--no-name`."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    docs = field_docs(cls)
    for spec in dataclasses.fields(cls):
        flag = f"--{spec.name.replace('_', '-')}"
        default = spec.default
        help_text = f"{docs.get(spec.name, '')} (default: {default!r})"
        if isinstance(default, bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default, help=help_text)
        else:
            parser.add_argument(flag, type=type(default), default=default, help=help_text)
    return cls(**vars(parser.parse_args(argv)))


# The frame-size-changing augmentations a pipeline may start with: their names (with RAD's aliases,
# as the server's parser accepts them), view, and default size (the paper's).
_VIEWS = {"crop": ("center_crop", 84), "random_crop": ("center_crop", 84), "translate": ("center_translate", 108)}


def evaluation_view(pipeline: str) -> str:
    """The deterministic view RAD evaluates with for an augmentation pipeline: `crop(84)` is evaluated
    on the centre crop, `translate(108)` on the centred frame (RAD's `center_crop_image` and
    `center_translate`), with the same defaults as the server (`crop` alone is crop(84)); other
    augmentations keep the frame size and need no view."""
    first = pipeline.split("|")[0].strip()
    match = re.fullmatch(r"(\w+)\s*(?:\(\s*(?:size\s*=\s*)?(\d*)\s*\))?", first)
    if not match or match.group(1).lower() not in _VIEWS:
        return ""
    view, default_size = _VIEWS[match.group(1).lower()]
    return f"{view}({match.group(2) or default_size})"


def select_device(name: str):
    """`auto`: the first CUDA device when there is one, else the CPU."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class RunLog:
    """A run directory: `args.json`, `metrics.csv` (step, wall time, name, value), TensorBoard events,
    and at the end `curve.png`."""

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

    def scalar(self, name: str, value: float, step: int) -> None:
        value = float(value)
        self._csv.writerow([step, f"{time.time() - self._start:.3f}", name, repr(value)])
        self._writer.add_scalar(name, value, step)

    def scalars(self, step: int, **named: float) -> None:
        """`scalars(step, **{"losses/qf_loss": 0.3})`."""
        for name, value in named.items():
            self.scalar(name, value, step)

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


def evaluate(envs, policy: Callable[[np.ndarray], np.ndarray], episodes: int) -> "list[float]":
    """Returns of `episodes` whole episodes of `policy` on the vector env `envs`, reset first.

    Every env contributes the same number of episodes (its first ones), so short episodes are not
    favoured over long ones; the extra envs' episodes are dropped."""
    per_env = math.ceil(episodes / envs.num_envs)
    counted = np.zeros(envs.num_envs, dtype=np.int64)
    returns: "list[list[float]]" = [[] for _ in range(envs.num_envs)]
    obs, _ = envs.reset()
    while counted.min() < per_env:
        obs, _, _, _, infos = envs.step(policy(obs))
        for i, (episode_return, _) in _ended_episodes(infos):
            if counted[i] < per_env:
                returns[i].append(episode_return)
                counted[i] += 1
    return in_rounds(returns, per_env)[:episodes]


def in_rounds(returns: "list[list[float]]", per_env: int) -> "list[float]":
    """Each env's first `per_env` returns (envs in order), the first of every env, then the second..."""
    return [r for round_ in range(per_env) for env_returns in returns for r in env_returns[round_:round_ + 1]]


def _ended_episodes(infos: dict) -> "list[tuple[int, tuple[float, int]]]":
    """(env, (return, length)) of every episode that ended in a step's infos: radserve's own
    figures, or gymnasium's RecordEpisodeStatistics' where an env has only those."""
    key = "radserve_episode" if "radserve_episode" in infos else "episode"
    if key not in infos:
        return []
    episodes = infos[key]
    return [(int(i), (float(episodes["r"][i]), int(episodes["l"][i]))) for i in np.flatnonzero(infos["_" + key])]


def episode_stats(infos: dict) -> "Iterable[tuple[float, int]]":
    """(return, length) of every episode that ended in a step's infos."""
    return [stats for _, stats in _ended_episodes(infos)]


def as_list(value) -> list:
    """An env's actor answers (`acting()`, `stop_acting()`): one server's, or a list of several."""
    return value if isinstance(value, list) else [value]


class ActedProgress:
    """What the servers' actors of `envs` report, polled (`--actor server`): the env steps acted since
    the last start_acting (summed over the servers), the episodes that ended since the last poll (from
    each actor's recent returns) as ((server, env), return), and an error as soon as one actor failed."""

    def __init__(self, envs) -> None:
        self.envs, self.seen = envs, {}
        self.infos: "dict[int, object]" = {}  # the last poll's answers by server position

    @property
    def acting(self) -> bool:
        """Whether an actor was acting at the last poll."""
        return any(info.state == "acting" for info in self.infos.values())

    def restarted(self) -> None:
        """A new start_acting: the actors count from zero again."""
        self.seen.clear()

    def poll(self) -> "tuple[int, list[tuple[tuple[int, int], float]]]":
        # None: a server lost now (a sharded env going on without it) or one with no policy yet.
        infos = {server: info for server, info in enumerate(as_list(self.envs.acting())) if info is not None}
        self.infos = infos
        failed = [info.error for info in infos.values() if info.state == "failed"]
        if failed:
            raise RuntimeError(f"a server's actor failed: {failed[0]}")
        ended = []
        for server, info in infos.items():
            if len(info.recent_envs) != len(info.recent_returns):
                raise RuntimeError("this server does not say which env each episode ended in (ActingInfo.recent_envs); "
                                   "it is older than this client")
            seen = self.seen.get(server, 0)
            # Fewer than seen: the server came back with a new session, whose actor counts from zero.
            new = min(info.episodes - seen if info.episodes >= seen else info.episodes, len(info.recent_returns))
            self.seen[server] = info.episodes
            first = len(info.recent_returns) - new
            ended += [((server, env), ret) for env, ret in zip(info.recent_envs[first:], info.recent_returns[first:])]
        return sum(info.env_steps for info in infos.values()), ended


def served_envs(envs) -> int:
    """How many of `envs` are served now: a sharded env going on without a lost server (its `active`
    mask) acts on the others' only."""
    active = getattr(envs, "active", None)
    return envs.num_envs if active is None else int(np.sum(active))


def evaluate_on_servers(envs, model: bytes, head: str, episodes: int, seed: int, deterministic: bool = True) -> "list[float]":
    """`evaluate` for `--actor server`: returns of `episodes` whole episodes the servers act with
    `model` on the vector env `envs`, reset first, with no Step call: each env's first episodes
    (the same number from every env, so short episodes are not favoured), taken with the head's
    deterministic action (`eval`) or, not `deterministic`, its draws."""
    per_env = math.ceil(episodes / envs.num_envs)
    envs.set_policy(model, head=head)
    envs.reset(seed=seed)
    envs.start_acting(eval=deterministic, seed=seed)
    progress = ActedProgress(envs)
    returns: "dict[tuple[int, int], list[float]]" = {}
    while sum(min(len(r), per_env) for r in returns.values()) < per_env * served_envs(envs):
        time.sleep(0.1)
        for env, episode_return in progress.poll()[1]:
            returns.setdefault(env, []).append(episode_return)
    envs.stop_acting()
    return in_rounds([returns[env] for env in sorted(returns)], per_env)[:episodes]


def learn_while_servers_act(envs, batches, *, update: Callable, policy: Callable[[], bytes], head: str,
                            policy_every: int, total_env_steps: int, eval_every: int, evaluate_at: Callable[[int], float],
                            log: "RunLog", env_steps_per_acted: int = 1, log_every: int = 50) -> "tuple[int, float]":
    """`--actor server`'s loop of an off-policy learner (the SAC examples), once the servers act on
    `envs`: `update(batch)` on every batch of `batches` (a stream whose rate limiter matches the
    actors'), `policy()` (ONNX bytes) sent as a new version every `policy_every` updates, the actors
    polled every 10 updates (their episodes logged, a failed one raised), `evaluate_at(env_steps)`
    every `eval_every` env steps (`env_steps_per_acted` env steps per acted step: the action repeat)
    and at the end, which is the first poll past `total_env_steps`; the actors are stopped then.
    Returns the env steps acted and the last evaluation's return."""
    from tqdm import tqdm

    progress = ActedProgress(envs)
    last_eval, last_return = evaluate_at(0), float("nan")
    next_eval, evaluated = eval_every, 0
    start, env_steps, metrics = time.perf_counter(), 0, {}
    bar = tqdm(total=total_env_steps, unit="env step", dynamic_ncols=True)
    try:
        for number, batch in enumerate(batches):
            metrics = update(batch)
            if (number + 1) % policy_every == 0:
                envs.set_policy(policy(), head=head)
            if number % 10 and number % log_every:
                continue
            acted, ended = progress.poll()
            acted *= env_steps_per_acted
            for _, episode_return in ended:
                last_return = episode_return
                log.scalars(acted, **{"charts/episodic_return": episode_return})
            bar.update(max(0, acted - env_steps))
            env_steps = acted
            sps = env_steps / (time.perf_counter() - start)
            if number % log_every == 0:
                versions = batch.policy_version[batch.policy_version >= 0] if batch.policy_version is not None else []
                # Versions between the policy that acted and the newest sent (random steps left out).
                staleness = float(np.mean(envs.policy_version - versions)) if len(versions) else 0.0
                log.scalars(env_steps, **metrics, **{"charts/SPS": sps, "charts/policy_staleness": staleness})
            bar.set_postfix(ret=f"{last_return:.0f}", eval=f"{last_eval:.0f}", sps=f"{sps:.0f}")
            if env_steps >= next_eval:
                next_eval += eval_every
                last_eval, evaluated = evaluate_at(env_steps), env_steps
            if env_steps >= total_env_steps:
                break
        envs.stop_acting()
        if evaluated != env_steps:
            last_eval = evaluate_at(env_steps)
    finally:
        bar.close()
    return env_steps, last_eval


def run_name(env_id: str, algorithm: str, seed: int) -> str:
    """CleanRL's run naming: env__algorithm__seed__unixtime (`/` in env ids becomes `-`)."""
    return f"{env_id.replace('/', '-')}__{algorithm}__{seed}__{int(time.time())}"
