"""The example programs, run as a user would, with a tiny budget (CleanRL's smoke tests)."""

import subprocess
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parent.parent / "client-py" / "examples"


def run_example(name, *args):
    return subprocess.run([sys.executable, str(EXAMPLES / name), *args], capture_output=True, text=True, timeout=240)


def test_the_demo_draws_augmented_batches_while_stepping():
    result = run_example("augmented_batches.py", "--batches", "5", "--batch-size", "16", "--initial-steps", "20",
                         "--num-envs", "2", "--workers", "1")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "5 augmented batches" in result.stdout and "frames each" in result.stdout


def test_the_random_agent_runs():
    result = run_example("random_agent.py", "--steps", "8", "--num-envs", "2", "--workers", "1",
                         "--render-profile", "fast")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "8 steps in" in result.stdout
