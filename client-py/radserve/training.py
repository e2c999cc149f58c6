"""What learners built on radserve share beyond the client: evaluation (acted here or on the
servers), the servers' actors followed as they act, and the loop of an off-policy learner while the
servers act. The example learners (client-py/examples) are built on it; what is a run's own (its
directory, metrics files, curves, command line) stays beside them, in `runs.py`.

    from radserve.training import ActorProgress, evaluate_on_servers, evaluation_view

`learn_while_servers_act` draws a progress bar with tqdm (the `examples` extra); nothing else here
needs more than the client.
"""

from __future__ import annotations

import math
import re
import time
from typing import Any, Callable, Iterable, Protocol

import numpy as np

from .types import Batches, SessionEnv

__all__ = ["ActorProgress", "ScalarLog", "episode_stats", "evaluate", "evaluate_on_servers", "evaluation_view",
           "in_rounds", "learn_while_servers_act", "served_envs"]

# The frame-size-changing augmentations a pipeline may start with: their names (with RAD's aliases,
# as the server's parser accepts them), view, and default size (the paper's).
_VIEWS = {"crop": ("center_crop", 84), "random_crop": ("center_crop", 84), "translate": ("center_translate", 108)}


def evaluation_view(pipeline: str) -> str:
    """The deterministic view RAD evaluates with for an augmentation pipeline: `crop(84)` is evaluated
    on the centre crop, `translate(108)` on the centred frame (RAD's `center_crop_image` and
    `center_translate`), with the same defaults as the server (`crop` alone is crop(84)); other
    augmentations keep the frame size and need no view (""). Pass it as `make_vec(observation_view=...)`."""
    first = pipeline.split("|")[0].strip()
    match = re.fullmatch(r"(\w+)\s*(?:\(\s*(?:size\s*=\s*)?(\d*)\s*\))?", first)
    if not match or match.group(1).lower() not in _VIEWS:
        return ""
    view, default_size = _VIEWS[match.group(1).lower()]
    return f"{view}({match.group(2) or default_size})"


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


def evaluate(envs: Any, policy: Callable[[np.ndarray], np.ndarray], episodes: int) -> "list[float]":
    """Returns of `episodes` whole episodes of `policy` acted here on the vector env `envs` (any
    gymnasium VectorEnv whose infos carry radserve's or RecordEpisodeStatistics' episode figures),
    reset first. Every env contributes the same number of episodes (its first ones), so short
    episodes are not favoured over long ones; the extra envs' episodes are dropped."""
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


class ActorProgress:
    """The servers' actors of `envs` as a learner follows them: the env steps acted since the last
    start_acting (summed over the servers), the episodes that ended since the last look (from each
    actor's recent returns) as ((server, env), return), and a failed actor raised at once."""

    def __init__(self, envs: SessionEnv) -> None:
        self.envs = envs
        self.seen: "dict[int, int]" = {}
        self.infos: "dict[int, Any]" = {}  # the last look's answers by server position

    @property
    def acting(self) -> bool:
        """Whether an actor was acting at the last look."""
        return any(info.state == "acting" for info in self.infos.values())

    def restarted(self) -> None:
        """A new start_acting: the actors count from zero again."""
        self.seen.clear()

    def poll(self) -> "tuple[int, list[tuple[tuple[int, int], float]]]":
        """One look at every server's actor: (env steps acted, episodes ended since the last look)."""
        # None: a server lost now (a sharded env going on without it) or one with no policy yet.
        infos = {server: info for server, info in enumerate(self.envs.acting()) if info is not None}
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

    def until_stopped(self, every: float = 0.02) -> "list[tuple[int, tuple[int, int], float]]":
        """Looks every `every` seconds until no actor acts (a rollout's `steps_per_env` reached):
        every episode that ended meanwhile as (env steps acted at the look that found it,
        (server, env), return). A look misses no episode as long as fewer than 100 end between two
        looks on one server (ActingInfo keeps the last 100)."""
        ended: "list[tuple[int, tuple[int, int], float]]" = []
        while True:
            time.sleep(every)
            acted, new = self.poll()
            ended += [(acted, env, episode_return) for env, episode_return in new]
            if not self.acting:  # that answer already held the last episodes
                return ended


def served_envs(envs: Any) -> int:
    """How many of `envs` are served now: a sharded env going on without a lost server (its `active`
    mask) acts on the others' only."""
    active = getattr(envs, "active", None)
    return envs.num_envs if active is None else int(np.sum(active))


def evaluate_on_servers(envs: SessionEnv, model: bytes, head: str, episodes: int, seed: int,
                        deterministic: bool = True) -> "list[float]":
    """`evaluate` acted by the servers: returns of `episodes` whole episodes the servers act with
    `model` on `envs`, reset first, with no Step call: each env's first episodes (the same number
    from every env, so short episodes are not favoured), taken with the head's deterministic action
    or, not `deterministic`, its draws."""
    per_env = math.ceil(episodes / envs.num_envs)
    envs.set_policy(model, head=head)
    envs.reset(seed=seed)
    envs.start_acting(deterministic=deterministic, seed=seed)
    progress = ActorProgress(envs)
    returns: "dict[tuple[int, int], list[float]]" = {}
    while sum(min(len(r), per_env) for r in returns.values()) < per_env * served_envs(envs):
        time.sleep(0.1)
        for env, episode_return in progress.poll()[1]:
            returns.setdefault(env, []).append(episode_return)
    envs.stop_acting()
    return in_rounds([returns[env] for env in sorted(returns)], per_env)[:episodes]


class ScalarLog(Protocol):
    """Where a learner's scalars go (the examples' RunLog): `scalars(step, **{"charts/SPS": 1e3})`."""

    def scalars(self, step: int, **named: float) -> None: ...


def learn_while_servers_act(envs: SessionEnv, batches: Batches, *, update: Callable, policy: Callable[[], bytes],
                            head: str, policy_every: int, total_env_steps: int, eval_every: int,
                            evaluate_at: Callable[[int], float], log: ScalarLog, env_steps_per_acted: int = 1,
                            log_every: int = 50, noise: "Callable[[], tuple[float, float, int, float]] | None" = None,
                            on_progress: "Callable[[int], None] | None" = None) -> "tuple[int, float]":
    """An off-policy learner's loop (the SAC examples' `--actor server`) once the servers act on
    `envs`: `update(batch)` on every batch of `batches` (a stream whose rate limiter matches the
    actors'), `policy()` (ONNX bytes) sent as a new version every `policy_every` updates, the actors
    looked at every 10 updates (their episodes logged, a failed one raised), `evaluate_at(env_steps)`
    every `eval_every` env steps (`env_steps_per_acted` env steps per acted step: the action repeat)
    and at the end, which is the first look past `total_env_steps`; the actors are stopped then.
    With `noise`, each version goes with the deterministic_noise head's schedule it returns then
    (DrQ-v2's current std); `on_progress(env_steps)` hears of every look at the actors.
    Returns the env steps acted and the last evaluation's return."""
    from tqdm import tqdm

    progress = ActorProgress(envs)
    last_eval, last_return = evaluate_at(0), float("nan")
    next_eval, evaluated = eval_every, 0
    start, env_steps, metrics = time.perf_counter(), 0, {}
    bar = tqdm(total=total_env_steps, unit="env step", dynamic_ncols=True)
    try:
        for number, batch in enumerate(batches):
            metrics = update(batch)
            if (number + 1) % policy_every == 0:
                envs.set_policy(policy(), head=head, **({"noise": noise()} if noise is not None else {}))
            if number % 10 and number % log_every:
                continue
            acted, ended = progress.poll()
            acted *= env_steps_per_acted
            for _, episode_return in ended:
                last_return = episode_return
                log.scalars(acted, **{"charts/episodic_return": episode_return})
            bar.update(max(0, acted - env_steps))
            env_steps = acted
            if on_progress is not None:
                on_progress(env_steps)
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
