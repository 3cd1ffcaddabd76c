"""The recipes in examples/ run end to end (two tiny epochs each) and print their per-epoch line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
TINY = ["--env-id", "SafetyHalfCheetahVelocity-v1", "--total-steps", "4000", "--steps-per-epoch", "2000",
        "--num-envs", "2"]


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    "script, args",
    [
        ("first_order.py", ["--algo", "focops", "--update-iters", "2"]),
        ("first_order.py", ["--algo", "ppo_lag", "--update-iters", "2", "--compile"]),
        ("second_order.py", ["--algo", "cpo", "--critic-iters", "2"]),
        ("torchrl_ppo_lag.py", ["--update-iters", "2"]),  # TorchRL's PPO recipe with PPOLagLoss
        ("sac_lag.py", ["--warmup-steps", "3000", "--batch-size", "64", "--hidden", "32"]),  # TorchRL's SAC loop
    ],
)
def test_recipe_runs(script, args):
    result = subprocess.run([sys.executable, str(EXAMPLES / script), *TINY, *args], capture_output=True, text=True,
                            timeout=110)
    assert result.returncode == 0, result.stderr[-2000:]
    lines = [line for line in result.stdout.splitlines() if line.startswith("epoch ")]
    assert len(lines) == 2 and "EpCost" in lines[-1] and "nan" not in lines[-1].lower()
