"""The example learners' run bookkeeping (client-py/examples/runs.py) that needs neither torch nor a
server, and their command lines (tyro, from an Args dataclass). What learners share beyond a run is
radserve.training, tested in client-py/tests/test_training.py."""

from dataclasses import dataclass

import numpy as np
import pytest
import tyro

from _procs import example

binned_mean = example("runs").binned_mean


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


def test_fields_document_themselves_and_become_flags(capsys):
    """The examples' command lines (`tyro.cli(Args)`): one --flag-name per field, documented by the
    field's docstring, booleans as --name/--no-name."""
    with pytest.raises(SystemExit):
        tyro.cli(Args, args=["--help"])
    usage = " ".join(capsys.readouterr().out.split())
    assert "a task" in usage and "transitions per minibatch" in usage and "bfloat16 convs" in usage
    args = tyro.cli(Args, args=["--batch-size", "32", "--lr", "0.5", "--amp"])
    assert args == Args(batch_size=32, lr=0.5, amp=True)
    assert tyro.cli(Args, args=["--no-amp"]).amp is False
    with pytest.raises(SystemExit):
        tyro.cli(Args, args=["--batch-size", "many"])


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
