"""radserve.training without a server: the evaluation view of a pipeline, evaluation acted here with
each env's first episodes, and ActorProgress following scripted actors (episodes found once, a
server that comes back counting from zero, a failed actor raised). The same functions against real
servers: tests/test_actors.py (evaluate_on_servers against evaluate) and the learners' smoke tests.
Also the loop while the servers act (learn_while_servers_act) against scripted actors."""

import numpy as np
import pytest

from radserve.actors import ActingInfo
from radserve.training import ActorProgress, evaluate, evaluation_view, in_rounds, served_envs


@pytest.mark.parametrize("pipeline, view", [
    ("crop(84)", "center_crop(84)"),
    ("translate(108)|grayscale(p=0.3)", "center_translate(108)"),
    ("crop(size=64)", "center_crop(64)"),
    ("translate", "center_translate(108)"),
    ("crop|grayscale", "center_crop(84)"),
    ("Random_Crop( 76 )", "center_crop(76)"),
    ("cutout_color", ""),
    ("none", ""),
    ("grayscale|crop(84)", ""),  # only a leading crop or translate changes the frame the policy sees
])
def test_the_evaluation_view_matches_the_training_augmentation(pipeline, view):
    assert evaluation_view(pipeline) == view


class ScriptedEnvs:
    """Two envs whose episodes end after fixed lengths: env 0 every 2 steps, env 1 every 5."""

    num_envs = 2

    def __init__(self):
        self.t = 0

    def reset(self):
        self.t = 0
        return np.zeros((2, 1)), {}

    def step(self, actions):
        self.t += 1
        ended = np.array([self.t % 2 == 0, self.t % 5 == 0])
        infos = {}
        if ended.any():
            infos = {"_episode": ended, "episode": {"r": np.array([2.0, 5.0]) + self.t, "l": np.array([2, 5])}}
        return np.zeros((2, 1)), np.zeros(2), ended, np.zeros(2, bool), infos


def test_evaluation_takes_the_same_number_of_episodes_from_every_env():
    returns = evaluate(ScriptedEnvs(), lambda obs: np.zeros(2), episodes=4)
    # env 0 ends at t=2, 4 (returns 4, 6); env 1 at t=5, 10 (returns 10, 15); the short episodes of
    # env 0 after its second are not counted.
    assert sorted(returns) == [4.0, 6.0, 10.0, 15.0]
    assert sorted(evaluate(ScriptedEnvs(), lambda obs: np.zeros(2), episodes=3)) == [4.0, 6.0, 10.0]


def acting(state="acting", env_steps=0, episodes=0, returns=(), envs=(), error=""):
    return ActingInfo(state=state, policy_version=1, acting_version=1, head="categorical", env_steps=env_steps,
                      episodes=episodes, recent_returns=list(returns), recent_envs=list(envs), error=error)


class ScriptedActors:
    """A sharded env of two servers whose actors answer what the test scripts, one list per look."""

    num_envs = 4

    def __init__(self, answers):
        self.answers = list(answers)

    def acting(self):
        return self.answers.pop(0)


def test_actor_progress_reports_each_episode_once_and_sums_the_servers():
    envs = ScriptedActors([
        [acting(env_steps=10, episodes=1, returns=[3.0], envs=[1]), acting(env_steps=8)],
        [acting(env_steps=20, episodes=3, returns=[3.0, 4.0, 5.0], envs=[1, 0, 1]), None],  # server 1 lost
        [acting(state="stopped", env_steps=30, episodes=3, returns=[3.0, 4.0, 5.0], envs=[1, 0, 1]),
         acting(env_steps=2, episodes=1, returns=[9.0], envs=[0])],  # server 1 back: a new session
    ])
    progress = ActorProgress(envs)
    assert progress.poll() == (18, [((0, 1), 3.0)])
    assert progress.acting
    assert progress.poll() == (20, [((0, 0), 4.0), ((0, 1), 5.0)])
    assert progress.poll() == (32, [((1, 0), 9.0)])
    assert progress.acting  # server 1's actor still acts


def test_actor_progress_follows_a_rollout_until_every_actor_stopped():
    envs = ScriptedActors([
        [acting(env_steps=4, episodes=1, returns=[1.0], envs=[2])],
        [acting(env_steps=8, episodes=2, returns=[1.0, 2.0], envs=[2, 3])],
        [acting(state="stopped", env_steps=12, episodes=3, returns=[1.0, 2.0, 7.0], envs=[2, 3, 0])],
    ])
    progress = ActorProgress(envs)
    assert progress.until_stopped(every=0.0) == [(4, (0, 2), 1.0), (8, (0, 3), 2.0), (12, (0, 0), 7.0)]
    assert not progress.acting and envs.answers == []
    progress.restarted()
    envs.answers = [[acting(env_steps=4, episodes=1, returns=[6.0], envs=[1])]]
    assert progress.poll() == (4, [((0, 1), 6.0)]), "a new start counts from zero"


def test_actor_progress_raises_a_failed_actor_and_an_older_server():
    failed = ScriptedActors([[acting(), acting(state="failed", error="the policy produced NaN")]])
    with pytest.raises(RuntimeError, match="produced NaN"):
        ActorProgress(failed).poll()
    older = ScriptedActors([[acting(episodes=1, returns=[1.0], envs=[])]])
    with pytest.raises(RuntimeError, match="older than this client"):
        ActorProgress(older).poll()


def test_rounds_and_served_envs():
    assert in_rounds([[1.0, 2.0], [3.0], [4.0, 5.0]], 2) == [1.0, 3.0, 4.0, 2.0, 5.0]
    assert served_envs(ScriptedActors([])) == 4
    sharded = ScriptedActors([])
    sharded.active = np.array([True, False, False, True])
    assert served_envs(sharded) == 2


class ScriptedLearning(ScriptedActors):
    """ScriptedActors that also take policies and stop: what learn_while_servers_act calls."""

    policy_version = 0

    def __init__(self, answers):
        super().__init__(answers)
        self.sent, self.stopped = [], False

    def set_policy(self, model, *, head, noise=None):
        self.policy_version += 1
        self.sent.append((model, head, noise))

    def stop_acting(self):
        self.stopped = True


class Log:
    def __init__(self):
        self.rows = []

    def scalars(self, step, **named):
        self.rows.append((step, named))


def test_the_loop_sends_versions_with_their_noise_and_evaluates_until_the_budget():
    """Every policy_every updates a version goes with the schedule noise() gives then; the actors are
    looked at every 10 updates, each look heard by on_progress; the first look past the budget stops
    them and evaluates."""
    from radserve.training import learn_while_servers_act

    looks = [[acting(env_steps=steps)] for steps in (0, 40, 80)]
    envs = ScriptedLearning(looks)
    batch = type("Batch", (), {"policy_version": np.array([-1, 0])})()
    stds = iter([0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3])
    seen, evaluated = [], []
    steps, last = learn_while_servers_act(
        envs, iter([batch] * 100), update=lambda b: {"losses/x": 1.0}, policy=lambda: b"onnx", head="deterministic_noise",
        policy_every=10, total_env_steps=100, eval_every=1000, evaluate_at=lambda s: evaluated.append(s) or 7.0,
        log=Log(), env_steps_per_acted=2, log_every=50, noise=lambda: (next(stds), 0.0, 1, 0.3),
        on_progress=seen.append)
    assert (steps, last) == (160, 7.0) and envs.stopped
    assert seen == [0, 80, 160], "a look every 10 updates, in env steps (2 per step acted)"
    assert evaluated == [0, 160]
    assert [noise[0] for _, _, noise in envs.sent] == [0.9, 0.8] and envs.answers == []
    assert all(head == "deterministic_noise" for _, head, _ in envs.sent)
