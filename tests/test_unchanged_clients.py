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


# ---------------------------------------------------------------------------- TorchRL's GymEnv
@pytest.mark.parametrize("env_id", ["SafetyPointGoal1Gymnasium-v0", "SafetyHalfCheetahVelocityGymnasium-v1"])
def test_gym_env_reads_the_cost_from_info(env_id):
    import gymnasium
    import numpy as np
    import torch
    from torchrl.envs import GymEnv, default_info_dict_reader

    import sg_torchrl  # noqa: F401 - registers the twin ids

    env = GymEnv(env_id)
    env.set_info_dict_reader(default_info_dict_reader(["cost"]))
    env.set_seed(0)
    rollout = env.rollout(6, break_when_any_done=False)
    assert ("next", "cost") in rollout.keys(True)
    # the same actions on a gymnasium twin seeded alike give the same costs
    twin = gymnasium.make(env_id)
    twin.reset(seed=0)
    expected = [twin.step(action.numpy())[4]["cost"] for action in rollout["action"]]
    assert all(type(cost) is np.float64 for cost in expected)
    torch.testing.assert_close(rollout["next", "cost"].reshape(-1).double(), torch.tensor(expected, dtype=torch.float64))
    # every key of the info (no key list) is readable too
    env_all = GymEnv(env_id)
    env_all.set_info_dict_reader(default_info_dict_reader())
    env_all.rollout(2)
    env.close()
    env_all.close()
    twin.close()


def test_gymnasium_conversion_info_is_torchrl_readable():
    import numpy as np

    import sg_torchrl.safety_gymnasium as safety_gymnasium
    from sg_torchrl.safety_gymnasium.wrappers import SafetyGymnasium2Gymnasium

    env = SafetyGymnasium2Gymnasium(safety_gymnasium.make("SafetyPointGoal1-v0"))
    env.reset(seed=0)
    info = env.step(env.action_space.sample())[4]
    assert type(info["cost"]) is np.float64 and all(hasattr(value, "dtype") for value in info.values())
    env.close()


# ---------------------------------------------------------------------------- python -m sg_torchrl.safety_gymnasium
WORKER_SCRIPT = '''
import multiprocessing as mp

import safety_gymnasium
from safety_gymnasium.wrappers import SafeAutoResetWrapper


def make_and_step(queue):
    env = SafeAutoResetWrapper(safety_gymnasium.make("SafetyPointGoal1-v0"))
    env.reset(seed=0)
    queue.put((safety_gymnasium.__name__, len(env.step(env.action_space.sample()))))
    env.close()


def share_worker(remote, parent_remote):
    # SafePO's multi-agent vector env worker: serves commands until "close", which its users
    # often never send (the daemon workers are left to die with the script).
    parent_remote.close()
    while True:
        command = remote.recv()
        remote.send(command)


if __name__ == "__main__":
    print("start method", mp.get_start_method())
    spawn = mp.get_context("spawn")
    queue = spawn.Queue()
    worker = spawn.Process(target=make_and_step, args=(queue,))
    worker.start()
    print("spawned", queue.get(timeout=300))
    worker.join()
    assert worker.exitcode == 0, worker.exitcode
    pipes = [mp.Pipe() for _ in range(2)]
    workers = [mp.Process(target=share_worker, args=(child, parent), daemon=True) for parent, child in pipes]
    for process in workers:
        process.start()
    for (parent, child) in pipes:
        child.close()
        parent.send("ping")
        assert parent.recv() == "ping"
    print("done")
'''


def test_launcher_alias_reaches_spawned_workers_and_workers_exit_cleanly(tmp_path):
    script = tmp_path / "train.py"
    script.write_text(WORKER_SCRIPT)
    result = run_python("", "-m", "sg_torchrl.safety_gymnasium", str(script), timeout=600)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr and "Error" not in result.stderr, result.stderr
    assert "spawned ('sg_torchrl.safety_gymnasium', 6)" in result.stdout and "done" in result.stdout
    expected = "spawn" if sys.platform in ("darwin", "win32") else "fork"
    assert f"start method {expected}" in result.stdout or sys.version_info >= (3, 14)


def test_launcher_exports_the_stand_in_to_subprocesses(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent('''
        import subprocess, sys
        code = "import safety_gymnasium.vector, sys; print(safety_gymnasium.__name__)"
        print(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
    '''))
    result = run_python("", "-m", "sg_torchrl.safety_gymnasium", "--start-method", "spawn", str(script))
    assert result.returncode == 0, result.stderr
    assert "sg_torchrl.safety_gymnasium" in result.stdout


# ---------------------------------------------------------------------------- losses on an agent group
def test_ppo_lag_loss_runs_on_the_agents_group_after_one_call():
    import torch
    from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
    from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor, ValueOperator

    import sg_torchrl
    from sg_torchrl.objectives import LagrangeMultiplier, PPOLagLoss

    torch.manual_seed(0)
    env = sg_torchrl.make("Safety2x3HalfCheetahVelocity-v0", num_envs=2, seed=0)
    obs_dim = env.observation_spec["agents", "observation"].shape[-1]
    act_dim = env.full_action_spec["agents", "action"].shape[-1]
    group_obs = [("agents", "observation")]
    actor = ProbabilisticActor(
        TensorDictModule(torch.nn.Sequential(MLP(in_features=obs_dim, out_features=act_dim, num_cells=[8]),
                                             AddStateIndependentNormalScale(act_dim)),
                         in_keys=group_obs, out_keys=[("agents", "loc"), ("agents", "scale")]),
        in_keys={"loc": ("agents", "loc"), "scale": ("agents", "scale")}, out_keys=[("agents", "action")],
        distribution_class=IndependentNormal, return_log_prob=True)
    critic = ValueOperator(MLP(in_features=obs_dim, out_features=1, num_cells=[8]), in_keys=group_obs,
                           out_keys=[("agents", "state_value")])
    cost_critic = ValueOperator(MLP(in_features=obs_dim, out_features=1, num_cells=[8]), in_keys=group_obs,
                                out_keys=[("agents", "cost_value")])
    loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(cost_limit=25.0))
    assert loss.set_group("agents") is loss  # the one call
    keys = loss.tensor_keys
    assert (keys.action, keys.reward, keys.cost, keys.done, keys.cost_advantage) == (
        ("agents", "action"), ("agents", "reward"), ("agents", "cost"), ("agents", "done"), ("agents", "cost_advantage"))
    loss.set_group("agents")  # idempotent
    assert keys.value == ("agents", "state_value")
    with torch.no_grad():
        rollout = env.rollout(5, actor)
    out = loss(rollout)
    total = sum(value for key, value in out.items() if key.startswith("loss_"))
    assert torch.isfinite(total)
    total.backward()
    assert all(parameter.grad is not None for parameter in actor.parameters())
    env.close()


def test_twin_ids_are_registered_when_gymnasium_is_probed_before_its_import():
    # TorchRL probes with importlib.util.find_spec("gymnasium") long before importing it.
    result = run_python("""
        import importlib.util
        import sg_torchrl
        assert importlib.util.find_spec("gymnasium") is not None
        import gymnasium
        gymnasium.spec("SafetyPointGoal1Gymnasium-v0")
        print("ok")
    """)
    assert result.returncode == 0 and "ok" in result.stdout, result.stderr


@pytest.mark.parametrize("first_use", ["rollout", "spec"])
def test_reward_sum_on_the_cost_says_to_use_episode_sum(first_use):
    """TorchRL's RewardSum reads reward-spec keys only; asked for the cost it now names EpisodeSum
    (before: a bare ``KeyError: 'cost'`` at reset, or a ValueError that said nothing of where the cost is)."""
    from torchrl.envs import RewardSum, TransformedEnv
    from torchrl.envs.utils import check_env_specs

    import sg_torchrl
    from sg_torchrl.envs import EpisodeSum

    env = TransformedEnv(sg_torchrl.make("SafetyPointGoal1-v0", num_envs=2), RewardSum(in_keys=["cost"]))
    with pytest.raises((KeyError, ValueError), match=r"sg_torchrl\.envs\.EpisodeSum\(in_keys=\['reward', 'cost'\]\)"):
        env.rollout(3) if first_use == "rollout" else env.full_observation_spec
    base = sg_torchrl.make("SafetyPointGoal1-v0", num_envs=2)
    assert base.reward_key == "reward"  # the cost stays out of the reward keys
    check_env_specs(base)
    summed = TransformedEnv(base, EpisodeSum(in_keys=["reward", "cost"])).rollout(3)
    assert summed["next", "episode_cost"].shape == (2, 3, 1)
