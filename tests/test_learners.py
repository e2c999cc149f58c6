"""The example learners, run as a user would with a tiny budget (CleanRL's smoke tests): each must
finish, write finite losses and evaluation returns to metrics.csv and TensorBoard, a checkpoint, and
its learning-curve PNG. Whether they learn is measured by bench/learning.py, not here.

They need the learners' extra (torch); `make test` installs it before running this file, with
RADSERVE_REQUIRE_TORCH=1 so that a missing torch fails instead of skipping.
"""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

if os.environ.get("RADSERVE_REQUIRE_TORCH") != "1":
    pytest.importorskip("torch", reason="the learners need the torch extra (make torch)")

from _procs import example

read_metrics = example("runs").read_metrics

EXAMPLES = Path(__file__).resolve().parent.parent / "client-py" / "examples"


def run_learner(script: str, runs_dir: Path, *flags: str) -> Path:
    result = subprocess.run([sys.executable, str(EXAMPLES / script), *flags, "--runs-dir", str(runs_dir),
                             "--workers", "1", "--torch-threads", "1", "--device", "cpu"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "evaluation return" in result.stdout
    (run_dir,) = runs_dir.iterdir()
    return run_dir


def check_run(run_dir: Path, expected_losses: "set[str]") -> dict:
    metrics = read_metrics(run_dir)
    losses = {name for name in metrics if name.startswith("losses/")}
    assert expected_losses <= losses, f"missing {expected_losses - losses}"
    for name in losses | {"charts/eval_return"}:
        steps, values = metrics[name]
        assert len(values) > 0 and all(math.isfinite(v) for v in values), f"{name}: {values}"
    assert len(metrics["charts/eval_return"][1]) >= 2, "evaluated at the start and at the end"
    assert (run_dir / "curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (run_dir / "checkpoint.pt").stat().st_size > 0
    assert any(path.name.startswith("events.out.tfevents") for path in run_dir.iterdir())
    assert (run_dir / "args.json").exists()
    return metrics


def test_rad_sac_from_pixels(tmp_path):
    run_dir = run_learner("sac_pixels.py", tmp_path, "--env", "dmc/cartpole-balance", "--aug", "translate(108)",
                          "--total-env-steps", "240", "--init-steps", "10", "--batch-size", "8", "--hidden-dim", "64",
                          "--eval-every", "240", "--eval-episodes", "2", "--render-profile", "fast", "--log-every", "1")
    metrics = check_run(run_dir, {"losses/critic_loss", "losses/actor_loss", "losses/alpha_loss", "losses/alpha"})
    # 30 agent steps at action repeat 8: the steps are counted in environment steps, like the paper.
    assert metrics["charts/eval_return"][0][-1] == 240
    # The one line `make demo` ends with: first and last evaluation, the curve's path.
    summary = (run_dir / "summary.txt").read_text()
    assert " at 0 -> " in summary and " at 240 environment steps" in summary and str(run_dir / "curve.png") in summary


def test_rad_sac_with_the_servers_acting(tmp_path):
    """--actor server: the policy is exported to ONNX and the server acts and evaluates with it; the
    learner only streams batches and sends new versions."""
    run_dir = run_learner("sac_pixels.py", tmp_path, "--actor", "server", "--env", "dmc/cartpole-balance",
                          "--aug", "translate(108)", "--total-env-steps", "240", "--init-steps", "10", "--batch-size", "8",
                          "--hidden-dim", "64", "--eval-every", "240", "--eval-episodes", "2", "--render-profile", "fast",
                          "--log-every", "1", "--policy-every", "5")
    metrics = check_run(run_dir, {"losses/critic_loss", "losses/actor_loss", "losses/alpha"})
    steps, staleness = metrics["charts/policy_staleness"]
    assert all(value >= 0 for value in staleness)
    assert metrics["charts/eval_return"][0][-1] >= 240


@pytest.mark.parametrize("actor", ["learner", "server"])
def test_drqv2_with_n_step_returns_and_the_servers_shift(tmp_path, actor):
    """DrQ-v2: batches shifted and summed over 3 steps by the server; with --actor server the actor
    goes as the deterministic_noise head, each version with the schedule's std."""
    run_dir = run_learner("drqv2_pixels.py", tmp_path, "--actor", actor, "--env", "dmc/cartpole-balance",
                          "--total-env-steps", "240", "--num-expl-steps", "10", "--batch-size", "8", "--hidden-dim", "64",
                          "--eval-every", "240", "--eval-episodes", "2", "--render-profile", "fast", "--log-every", "1",
                          "--policy-every", "5", "--std-steps", "200")
    metrics = check_run(run_dir, {"losses/critic_loss", "losses/actor_loss", "losses/std"})
    steps, stds = metrics["losses/std"]
    assert stds[0] > stds[-1] >= 0.1, "the exploration std follows its linear schedule down"
    assert metrics["charts/eval_return"][0][-1] >= 240


def test_rad_sac_crop_with_bfloat16_convs(tmp_path):
    run_dir = run_learner("sac_pixels.py", tmp_path, "--env", "dmc/cartpole-balance", "--aug", "crop(84)|grayscale(p=0.5)",
                          "--amp", "--total-env-steps", "160", "--init-steps", "10", "--batch-size", "8",
                          "--hidden-dim", "64", "--eval-every", "160", "--eval-episodes", "1", "--render-profile", "fast",
                          "--log-every", "1")
    check_run(run_dir, {"losses/critic_loss", "losses/actor_loss"})


def test_sac_from_states_with_amplitude_scaling(tmp_path):
    run_dir = run_learner("sac_state.py", tmp_path, "--env", "gym/InvertedPendulum-v5", "--aug", "ras_s",
                          "--total-steps", "300", "--learning-starts", "50", "--batch-size", "32",
                          "--eval-every", "300", "--eval-episodes", "2", "--log-every", "50")
    check_run(run_dir, {"losses/qf_loss", "losses/actor_loss", "losses/alpha_loss"})


def test_discrete_sac_on_cartpole_with_noise(tmp_path):
    run_dir = run_learner("sac_state.py", tmp_path, "--env", "gym/CartPole-v1", "--aug", "noise(std=0.05)",
                          "--total-steps", "200", "--learning-starts", "50", "--batch-size", "32",
                          "--eval-every", "200", "--eval-episodes", "2", "--log-every", "50")
    check_run(run_dir, {"losses/qf_loss", "losses/actor_loss", "losses/alpha_loss"})


def test_dqn_with_prioritized_n_step_replay(tmp_path):
    """Prioritized 3-step batches from the server; the learner's |TD errors| go back as priorities and
    beta follows its schedule up to 1."""
    run_dir = run_learner("dqn_prioritized.py", tmp_path, "--env", "gym/CartPole-v1", "--total-steps", "300",
                          "--learning-starts", "100", "--batch-size", "16", "--eval-every", "300", "--eval-episodes", "2",
                          "--log-every", "50", "--target-every", "20")
    metrics = check_run(run_dir, {"losses/td_loss", "losses/q_values", "losses/mean_weight"})
    steps, betas = metrics["charts/beta"]
    assert betas[0] < betas[-1] <= 1.0, "beta anneals towards 1"
    weights = metrics["losses/mean_weight"][1]
    assert ((weights > 0) & (weights <= 1)).all(), "importance weights are scaled by the batch's largest"


def test_ppo_on_procgen_with_rollouts(tmp_path):
    run_dir = run_learner("ppo_procgen.py", tmp_path, "--env", "procgen/bigfish", "--aug", "crop(56)",
                          "--num-envs", "4", "--num-steps", "16", "--num-minibatches", "2", "--total-timesteps", "128",
                          "--eval-every", "128", "--eval-episodes", "2", "--num-levels", "10")
    metrics = check_run(run_dir, {"losses/policy_loss", "losses/value_loss", "losses/entropy", "losses/approx_kl"})
    assert list(metrics["losses/policy_loss"][0]) == [64, 128], "one log per rollout of 4 envs x 16 steps"


def test_sac_from_states_with_the_servers_acting(tmp_path):
    run_dir = run_learner("sac_state.py", tmp_path, "--actor", "server", "--env", "gym/InvertedPendulum-v5",
                          "--total-steps", "300", "--learning-starts", "50", "--batch-size", "32",
                          "--eval-every", "300", "--eval-episodes", "2", "--log-every", "20", "--policy-every", "10")
    metrics = check_run(run_dir, {"losses/qf_loss", "losses/actor_loss", "losses/alpha_loss"})
    assert metrics["charts/eval_return"][0][-1] >= 300
    assert all(value >= 0 for value in metrics["charts/policy_staleness"][1])


def test_ppo_with_the_servers_acting(tmp_path):
    """--actor server: each rollout is acted by the server with the policy sent before it; the learner
    reads the rollout's log-probabilities and values instead of computing its own."""
    run_dir = run_learner("ppo_procgen.py", tmp_path, "--actor", "server", "--env", "procgen/bigfish", "--aug", "crop(56)",
                          "--num-envs", "4", "--num-steps", "16", "--num-minibatches", "2", "--total-timesteps", "128",
                          "--eval-every", "128", "--eval-episodes", "2", "--num-levels", "10")
    metrics = check_run(run_dir, {"losses/policy_loss", "losses/value_loss", "losses/entropy", "losses/approx_kl"})
    assert list(metrics["losses/policy_loss"][0]) == [64, 128], "one log per rollout of 4 envs x 16 steps"


def test_an_unknown_augmentation_is_refused_before_training(tmp_path):
    result = subprocess.run([sys.executable, str(EXAMPLES / "sac_state.py"), "--env", "gym/InvertedPendulum-v5",
                             "--aug", "ras_x", "--total-steps", "100", "--runs-dir", str(tmp_path), "--workers", "1"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode != 0
    assert "ras_x" in result.stderr and "ras_s" in result.stderr, result.stderr[-2000:]


GYMNASIUM_SCRIPT = Path(__file__).resolve().parent / "scripts" / "ppo_continuous_action.py"


def run_gymnasium_script(out: Path, *flags: str) -> dict:
    result = subprocess.run([sys.executable, str(GYMNASIUM_SCRIPT), "--env-id", "Hopper-v5", "--total-timesteps",
                             "3072", "--num-steps", "1024", "--out", str(out), *flags],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(out.read_text())


def test_a_gymnasium_script_runs_with_only_its_env_line_changed(tmp_path, server):
    """A PPO script in the shape of CleanRL's ppo_continuous_action.py, whose wrappers are gymnasium's
    vector wrappers (FlattenObservation and NormalizeObservation require NextStep autoreset), run twice
    from the same seed: on gymnasium's own SyncVectorEnv and on radserve with make_vec's defaults, the
    env line the only difference. radserve's default autoreset is gymnasium's, so the wrappers accept it;
    and as its envs step as gymnasium's do, the two runs train alike: the same episodes, with returns and
    losses equal up to float32 rounding (radserve serves MuJoCo states as float32, gymnasium as float64,
    so the policy's inputs differ in their last bits)."""
    local = run_gymnasium_script(tmp_path / "gymnasium.json")
    remote = run_gymnasium_script(tmp_path / "radserve.json", "--radserve", server.address)
    assert remote["autoreset_mode"] == local["autoreset_mode"] == "NextStep"
    assert remote["global_step"] == 3072
    episodes = remote["episodes"]
    # A random Hopper falls within tens of steps: RecordEpisodeStatistics saw many episodes end.
    assert len(episodes["return"]) >= 20, episodes
    assert sum(episodes["length"]) <= 3072 and all(length >= 1 for length in episodes["length"])
    # The wrapper's returns are radserve's own figures for the same episodes (the env's rewards,
    # under the reward normalisation that comes after RecordEpisodeStatistics).
    assert np.allclose(episodes["return"], episodes["radserve_return"], rtol=1e-5, atol=1e-5)
    # Step for step the same episodes, losses and learning as on gymnasium's own vector env.
    assert episodes["length"] == local["episodes"]["length"]
    assert np.allclose(episodes["return"], local["episodes"]["return"], rtol=1e-4)
    assert np.allclose(remote["losses"], local["losses"], rtol=1e-3, atol=1e-6)
