"""``copy.deepcopy`` and ``pickle`` of an env built by ``sg_torchrl.make`` continue its simulators exactly.

Numpy views are copied as separate arrays, so a copy made attribute by attribute would hold caches,
buffers and control views that no longer alias its ``MjData`` (the copy's next step
differed). ``SafeEnv.__reduce_ex__`` rebuilds the env and loads its ``sim_state`` instead.
"""

from __future__ import annotations

import copy
import pickle

import pytest
import torch

import sg_torchrl

IDS = ["SafetyHalfCheetahVelocity-v1", "SafetyAntVelocity-v1", "SafetyPointGoal1-v0", "SafetyCarButton1-v0",
       "Safety2x3HalfCheetahVelocity-v0"]


def _copies(env):
    return {"deepcopy": copy.deepcopy(env), "pickle": pickle.loads(pickle.dumps(env)),
            "copy of a copy": copy.deepcopy(copy.deepcopy(env))}


def _steps(env, td, actions):
    outputs = []
    for action in actions:
        td = env.step_and_maybe_reset(td.set("action", action))[1]
        outputs.append(td.exclude("action").clone())
    return outputs


@pytest.mark.parametrize("num_envs", [1, 3])
@pytest.mark.parametrize("env_id", IDS)
def test_copies_continue_the_simulators_exactly(env_id, num_envs):
    env = sg_torchrl.make(env_id, num_envs=num_envs, seed=0)
    td = env.reset()
    for _ in range(7):
        td = env.rand_step(td)
        td = env.step_and_maybe_reset(td)[1]
    torch.manual_seed(1)
    actions = [env.action_spec.rand() for _ in range(40)]  # long enough to cross resets on some ids
    copies = _copies(env)
    expected = _steps(env, td.clone(), actions)
    for name, clone in copies.items():
        got = _steps(clone, td.clone(), actions)
        for step, (a, b) in enumerate(zip(expected, got)):
            assert (a == b).all(), f"{name} of {env_id} (N={num_envs}) differs at step {step}"
        clone.close()
    env.close()


def test_envs_built_without_make_copy_attribute_by_attribute():
    from sg_torchrl.envs.velocity import VelocityEnv

    env = VelocityEnv("HalfCheetah", num_envs=1, seed=0)
    assert "_construction" not in env.__dict__
    clone = copy.deepcopy(env)  # the generic copy still works (no rebuild recipe to follow)
    assert type(clone) is VelocityEnv and clone is not env


@pytest.mark.parametrize("env_id", ["SafetyAntVelocity-v1", "SafetyHumanoidVelocity-v1"])
def test_copies_mid_episode_continue_the_reward_exactly(env_id):
    # Mid-episode (not just after a reset), with one simulator reset between the copy and its first
    # step: the copy's rewards (x/y velocity) equal the original's from the first step on.
    env = sg_torchrl.make(env_id, num_envs=2, seed=0)
    generator = torch.Generator().manual_seed(0)
    actions = [torch.rand(env.action_spec.shape, generator=generator) * 2 - 1 for _ in range(6)]
    td = _steps(env, env.reset(), actions[:3])[-1]
    twin = copy.deepcopy(env)
    reset = td.clone().set("_reset", torch.tensor([[True], [False]]))
    roots = [env.reset(reset.clone()), twin.reset(reset.clone())]
    for action in actions[3:]:
        steps = [made.step(root.set("action", action)) for made, root in zip((env, twin), roots)]
        torch.testing.assert_close(steps[0]["next"], steps[1]["next"], rtol=0, atol=0)
        roots = [step["next"].exclude("reward", "cost") for step in steps]
    env.close()
    twin.close()
