"""EpisodeSum: RewardSum that also accumulates observation-spec entries (cost, cost_info)."""

import sys
from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)
sys.path.insert(0, str(Path(__file__).parent))

from mock_envs import CountingCostEnv, expected_episode, expected_step_costs  # noqa: E402
from torchrl.envs import Compose, RewardSum, StepCounter, TransformedEnv  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

from sg_torchrl.envs.transforms import EpisodeSum  # noqa: E402

IN_KEYS = ["reward", "cost", ("cost_info", "odd"), ("cost_info", "third")]
OUT_KEYS = [
    "episode_reward",
    "episode_cost",
    ("episode_cost_info", "odd"),
    ("episode_cost_info", "third"),
]


def make_env(num_envs=4, max_steps=None, counter_first=True):
    steps = StepCounter(max_steps=max_steps)
    sums = EpisodeSum(in_keys=IN_KEYS, out_keys=OUT_KEYS)
    chain = Compose(steps, sums) if counter_first else Compose(sums, steps)
    return TransformedEnv(CountingCostEnv(num_envs), chain)


def test_reward_sum_rejects_observation_spec_cost():
    # The reason EpisodeSum exists: cost lives in the observation spec.
    env = TransformedEnv(CountingCostEnv(2), RewardSum(in_keys=["reward", "cost"]))
    with pytest.raises(ValueError, match="reward spec"):
        env.observation_spec


@pytest.mark.parametrize("counter_first", [True, False])
def test_check_env_specs(counter_first):
    env = make_env(counter_first=counter_first)
    check_env_specs(env)
    spec = env.observation_spec
    for key in OUT_KEYS:
        assert spec[key].shape == (4, 1)
        assert spec[key].dtype == torch.float32
    assert spec["episode_cost_info"].shape == (4,)
    assert env.reward_keys == ["reward"]


def test_unknown_in_key_raises():
    env = TransformedEnv(CountingCostEnv(2), EpisodeSum(in_keys=["nope"]))
    with pytest.raises(ValueError, match="neither in the reward spec"):
        env.observation_spec


@pytest.mark.parametrize("max_steps", [None, 4])
def test_episode_sums_at_done(max_steps):
    env = make_env(max_steps=max_steps)
    td = env.rollout(20, break_when_any_done=False)  # partial resets of the done sub-envs
    nxt = td["next"]
    reset = env.reset()
    for key in OUT_KEYS:
        assert (reset[key] == 0).all()
    ends = 0
    for i in range(4):
        length = 3 + i if max_steps is None else min(3 + i, max_steps)
        step_costs = torch.tensor(expected_step_costs(length))
        expected = expected_episode(length)
        for t in range(20):
            k = t % length  # step index within the episode, 0-based
            assert nxt["step_count"][i, t].item() == k + 1
            assert nxt["episode_reward"][i, t].item() == k + 1
            assert nxt["episode_cost"][i, t].item() == step_costs[: k + 1].sum().item()
            done = bool(nxt["done"][i, t])
            assert done == (k == length - 1)
            if done:
                ends += 1
                assert nxt["episode_reward"][i, t].item() == expected["return"]
                assert nxt["episode_cost"][i, t].item() == expected["cost"]
                odd = nxt["episode_cost_info", "odd"][i, t].item()
                third = nxt["episode_cost_info", "third"][i, t].item()
                assert odd == expected["cost_info/odd"]
                assert third == expected["cost_info/third"]
    assert ends > 0
