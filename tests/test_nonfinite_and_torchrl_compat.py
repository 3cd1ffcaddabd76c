"""Trustworthy transitions and stock TorchRL compatibility.

* A reward or cost that would be emitted non-finite (e.g. the velocity tasks' control cost of a huge
  but finite action, ``-inf`` once cast to float32) is handled like a physics error by the shared
  ``SafeEnv`` step: that simulator is truncated, counted in ``physics_errors`` and its reward and
  cost are zeroed; the other simulators' transitions are those of a run without the bad action.
* Stock ``torchrl.envs.GymEnv`` builds our gymnasium ids: it passes ``frameskip`` and drops it only
  when the ``TypeError`` uses Python's wording for an unknown keyword.
* Stock ``ToTensorImage`` applies to our ``pixels``: they are TorchRL's raw pixels, channels-last uint8.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchrl.envs import GymEnv, ToTensorImage, TransformedEnv
from torchrl.envs.utils import check_env_specs

import sg_torchrl
import sg_torchrl.gym

torch.set_num_threads(1)

HUGE = 1e20  # finite, accepted as an action; its squared control cost overflows float32


def _step_both(env, twin, action_key, actions, bad_step, corrupt):
    """Step ``env`` and ``twin`` through ``actions``; ``corrupt(action)`` is applied to ``env``'s at ``bad_step``.

    Returns the outputs of both, per step.
    """
    td, td_twin = env.reset(), twin.reset()
    outs, refs = [], []
    for t, action in enumerate(actions):
        mine = corrupt(action.clone()) if t == bad_step else action
        out = env.step(td.set(action_key, mine))["next"]
        ref = twin.step(td_twin.set(action_key, action))["next"]
        outs.append(out.clone())
        refs.append(ref.clone())
        td, td_twin = out.clone(), ref.clone()
    return outs, refs


def _uniform(shape, seed):
    return 2 * torch.rand(shape, generator=torch.Generator().manual_seed(seed)) - 1


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no overflow warning from a float32 cast either
def test_huge_action_isolates_one_velocity_simulator():
    env = sg_torchrl.make("SafetyHalfCheetahVelocity-v1", num_envs=3, seed=3)
    twin = sg_torchrl.make("SafetyHalfCheetahVelocity-v1", num_envs=3, seed=3)
    actions = _uniform((5, 3, 6), seed=1)

    def corrupt(action):
        action[1, 0] = HUGE
        return action

    outs, refs = _step_both(env, twin, "action", actions, bad_step=2, corrupt=corrupt)
    bad = outs[2]
    assert bad["truncated"].squeeze(-1).tolist() == [False, True, False]
    assert bad["done"].squeeze(-1).tolist() == [False, True, False]
    assert bad["reward"][1].item() == 0.0 and bad["cost"][1].item() == 0.0
    assert env.physics_errors == 1 and twin.physics_errors == 0
    for out, ref in zip(outs, refs):
        for key in ("observation", "reward", "cost", ("cost_info", "velocity"), "done", "terminated", "truncated"):
            assert torch.isfinite(out[key].float()).all(), key
            torch.testing.assert_close(out[key][[0, 2]], ref[key][[0, 2]], rtol=0, atol=0)
    assert env._elapsed.tolist() == [5, 2, 5]  # the isolated simulator restarted its episode


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_huge_action_isolates_one_multi_agent_velocity_simulator():
    env = sg_torchrl.make("Safety2x3HalfCheetahVelocity-v0", num_envs=3, seed=3)
    twin = sg_torchrl.make("Safety2x3HalfCheetahVelocity-v0", num_envs=3, seed=3)
    actions = _uniform((5, 3, 2, 3), seed=1)

    def corrupt(action):
        action[1, 0, 0] = HUGE
        return action

    outs, refs = _step_both(env, twin, ("agents", "action"), actions, bad_step=2, corrupt=corrupt)
    bad = outs[2]
    assert bad["truncated"].squeeze(-1).tolist() == [False, True, False]
    assert bad["agents", "truncated"][1].all() and not bad["agents", "truncated"][[0, 2]].any()
    assert (bad["agents", "reward"][1] == 0).all() and (bad["agents", "cost"][1] == 0).all()
    assert env.physics_errors == 1
    keys = (("agents", "observation"), ("agents", "reward"), ("agents", "cost"), ("agents", "done"), "state",
            "cost", "done")
    for out, ref in zip(outs, refs):
        for key in keys:
            assert torch.isfinite(out[key].float()).all(), key
            torch.testing.assert_close(out[key][[0, 2]], ref[key][[0, 2]], rtol=0, atol=0)


@pytest.mark.parametrize("cost_mode", ["indicator", "raw"])
@pytest.mark.parametrize("bad_value", [np.inf, np.nan])
def test_nonfinite_cost_isolates_one_navigation_simulator(cost_mode, bad_value):
    # A cost hook gone wrong: under "indicator" inf would read 1 and NaN 0, hiding the fault.
    env = sg_torchrl.make("SafetyPointGoal1-v0", num_envs=3, seed=0, cost_mode=cost_mode)
    td = env.reset()
    compute_cost = env._compute_cost

    def broken_cost():
        costs = compute_cost()
        name = next(iter(costs))
        costs[name] = costs[name].copy()
        costs[name][2] = bad_value
        return costs

    env._compute_cost = broken_cost
    out = env.step(td.set("action", torch.zeros(3, 2)))["next"]
    assert out["truncated"].squeeze(-1).tolist() == [False, False, True]
    assert out["cost"][2].item() == 0.0 and out["reward"][2].item() == 0.0
    assert all(torch.isfinite(value).all() for value in out["cost_info"].values())
    assert env.physics_errors == 1


def test_cost_total_overflowing_float32_is_isolated():
    # Each raw cost fits float32, their emitted sum does not.
    env = sg_torchrl.make("SafetyHalfCheetahVelocity-v1", num_envs=2, seed=0, cost_mode="raw")
    env.reset()
    big = float(np.finfo(np.float32).max)
    env._compute_cost = lambda: {"velocity": np.array([1.0, big]), "other": np.array([0.0, big])}
    observation, reward, costs, terminated, truncated = env._transition_arrays(np.zeros((2, 6)))
    assert truncated.tolist() == [False, True] and env.physics_errors == 1
    assert costs["velocity"].tolist() == [1.0, 0.0]


def test_gym_facade_truncates_a_huge_action():
    env = sg_torchrl.gym.make("SafetyHalfCheetahVelocity-v1")
    env.reset(seed=0)
    action = np.zeros(6)
    action[0] = HUGE
    obs, reward, cost, terminated, truncated, info = env.step(action)
    assert truncated and not terminated and reward == 0.0 and cost == 0.0
    assert env.torchrl_env.physics_errors == 1
    env.close()


# ---------------------------------------------------------------------------- stock TorchRL GymEnv
def test_stock_gym_env_builds_and_steps_a_twin_id():
    env = GymEnv("SafetyPointGoal1Gymnasium-v0")
    check_env_specs(env)
    env.set_seed(0)
    rollout = env.rollout(20)
    assert rollout.batch_size == (20,)
    assert rollout["next", "observation"].shape == (20, 60)
    assert torch.isfinite(rollout["next", "reward"]).all()
    env.close()


def test_stock_gym_env_frame_skip_is_done_by_the_wrapper():
    # TorchRL's fallback: the env rejects ``frameskip``, the wrapper repeats the action itself.
    env = GymEnv("SafetyHalfCheetahVelocityGymnasium-v1", frame_skip=2)
    assert env.wrapper_frame_skip == 2
    assert env.rollout(3)["next", "observation"].shape == (3, 17)
    env.close()


def test_unknown_option_uses_pythons_wording():
    with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'") as error:
        sg_torchrl.gym.make("SafetyPointGoal1Gymnasium-v0", frameskip=1)
    assert "max_episode_steps" in str(error.value)  # still says what the env takes
    with pytest.raises(TypeError, match="unexpected keyword argument 'bogus'"):
        sg_torchrl.gym.make("SafetyHalfCheetahVelocity-v1", bogus=3, width=64)
    # What sg_torchrl.make takes besides the env's options, and the façade's render options, still pass.
    sg_torchrl.gym.make("SafetyPointGoal1Gymnasium-v0", seed=0, device="cpu", max_episode_steps=5, width=32).close()


# ---------------------------------------------------------------------------- stock TorchRL ToTensorImage
def test_stock_to_tensor_image_on_our_pixels(backend):
    # Our pixels follow TorchRL's raw-pixel convention (channels-last uint8), so the stock transform,
    # without shape_tolerant or any other option, gives channels-first floats in [0, 1].
    base = sg_torchrl.make("SafetyPointGoal1Vision-v0", num_envs=2, seed=0, image_size=16)
    assert base.observation_spec["pixels"].shape == (2, 16, 16, 3)
    env = TransformedEnv(base, ToTensorImage(in_keys=["pixels"]))
    spec = env.observation_spec["pixels"]
    assert spec.shape == (2, 3, 16, 16) and spec.dtype == torch.float32
    check_env_specs(env, seed=0)
    rollout = env.rollout(3)
    for pixels in (rollout["pixels"], rollout["next", "pixels"]):
        assert pixels.shape == (2, 3, 3, 16, 16) and pixels.dtype == torch.float32
        assert 0 <= pixels.min() and pixels.max() <= 1 and pixels.std() > 0.01
    env.close()
