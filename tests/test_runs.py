"""The example learners' shared bookkeeping (client-py/examples/runs.py) that needs neither torch nor a
server."""

from dataclasses import dataclass

import numpy as np
import pytest

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "client-py" / "examples"))
from runs import binned_mean, evaluate, evaluation_view, field_docs, parse_args  # noqa: E402


@dataclass
class Args:
    env: str = "dmc/cartpole-swingup"
    """a task"""
    batch_size: int = 512
    """transitions per
    minibatch"""
    lr: float = 1e-3
    amp: bool = False
    """bfloat16 convs"""


def test_fields_document_themselves_and_become_flags():
    assert field_docs(Args) == {"env": "a task", "batch_size": "transitions per minibatch", "amp": "bfloat16 convs"}
    args = parse_args(Args, argv=["--batch-size", "32", "--lr", "0.5", "--amp"])
    assert args == Args(batch_size=32, lr=0.5, amp=True)
    assert parse_args(Args, argv=["--no-amp"]).amp is False
    with pytest.raises(SystemExit):
        parse_args(Args, argv=["--batch-size", "many"])


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


def test_binned_mean_averages_each_bin_at_its_mean_step():
    steps = np.array([0, 10, 20, 90, 100])
    values = np.array([1.0, 3.0, 5.0, 7.0, 9.0])
    centres, means = binned_mean(steps, values, bins=2)  # bins [0, 50) and [50, 100]
    np.testing.assert_allclose(centres, [10.0, 95.0])
    np.testing.assert_allclose(means, [3.0, 8.0])


def test_binned_mean_drops_empty_bins_and_accepts_no_data():
    centres, means = binned_mean(np.array([0, 100]), np.array([2.0, 4.0]), bins=10)
    np.testing.assert_allclose(centres, [0.0, 100.0])
    np.testing.assert_allclose(means, [2.0, 4.0])
    assert binned_mean(np.array([]), np.array([]))[0].size == 0
