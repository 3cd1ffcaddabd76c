"""Clients of Safety-Gymnasium used unchanged on sg_torchrl: gymnasium's registry and checker, TorchRL's
``GymEnv`` and transforms, SafePO's process layout and losses (emulated: SafePO and OmniSafe are not
installed here)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_python(code: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run ``python <args> -c code`` (or ``python <args>`` when ``code`` is empty) from the repository root."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    command = [sys.executable, *args] + (["-c", textwrap.dedent(code)] if code else [])
    return subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)


# ---------------------------------------------------------------------------- gymnasium's registry
@pytest.mark.parametrize("first", ["sg_torchrl", "gymnasium"])
def test_twin_ids_are_registered_on_import(first):
    second = "gymnasium" if first == "sg_torchrl" else "sg_torchrl"
    result = run_python(f"""
        import sys
        import {first}, {second}
        import gymnasium
        assert "sg_torchrl.gym" not in sys.modules and "torch" not in sys.modules and "mujoco" not in sys.modules
        assert gymnasium.spec("SafetyPointGoal1Gymnasium-v0").max_episode_steps == 1000
        assert gymnasium.spec("SafetyAntVelocity-v1").disable_env_checker
        env = gymnasium.make("SafetyPointGoal1Gymnasium-v0")
        obs, info = env.reset(seed=0)
        assert "cost" in env.step(env.action_space.sample())[4]
        print("ok")
    """)
    assert result.returncode == 0 and "ok" in result.stdout, result.stderr


def test_twin_ids_are_registered_by_the_drop_in_import():
    result = run_python("""
        import sys
        import sg_torchrl.safety_gymnasium, gymnasium
        assert "sg_torchrl.gym" not in sys.modules
        gymnasium.spec("SafetyCarButton2Gymnasium-v0")
        print("ok")
    """)
    assert result.returncode == 0 and "ok" in result.stdout, result.stderr
