"""Tests of the reward / cost GAE factories and SafePO's advantage normalisation."""
from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402
from tensordict.nn import TensorDictModule  # noqa: E402

from sg_torchrl.objectives import make_cost_gae, make_gae, normalize_advantages  # noqa: E402

GAMMA, LMBDA = 0.9, 0.8  # not the defaults, so that the factories must pass them through

# One env, 7 steps. Step 2 terminates (goal/failure: no bootstrap), step 4 is truncated by a time
# limit (bootstrap from the final observation), step 6 is cut off by the end of the batch.
# After each episode end the next observation is a fresh reset observation, unrelated to the
# final observation stored under "next".
OBS = [0.5, 1.0, 1.5, 0.2, 0.4, 0.1, 0.3]
NEXT_OBS = [1.0, 1.5, 2.0, 0.4, 0.6, 0.3, 0.35]
REWARD = [1.0, -0.5, 2.0, 0.3, 0.0, 1.2, -1.0]
COST = [0.0, 1.0, 1.0, 0.0, 1.0, 0.0, 1.0]
TERMINATED = [False, False, True, False, False, False, False]
TRUNCATED = [False, False, False, False, True, False, False]


# --------------------------------------------------------------------------- helpers
def make_linear_critic(out_key: str, weight: float, bias: float) -> TensorDictModule:
    """A critic V(s) = weight * s + bias, so the expected values are known exactly."""
    net = torch.nn.Linear(1, 1)
    with torch.no_grad():
        net.weight.fill_(weight)
        net.bias.fill_(bias)
    return TensorDictModule(net, in_keys=["observation"], out_keys=[out_key])


def make_trajectory() -> TensorDict:
    def col(values, dtype=torch.float32):
        return torch.tensor(values, dtype=dtype).unsqueeze(-1)

    terminated = col(TERMINATED, torch.bool)
    truncated = col(TRUNCATED, torch.bool)
    return TensorDict(
        {
            "observation": col(OBS),
            "next": {
                "observation": col(NEXT_OBS),
                "reward": col(REWARD),
                "cost": col(COST),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            },
        },
        batch_size=[len(OBS)],
    )


def hand_gae(signal, weight, bias, gamma=GAMMA, lmbda=LMBDA):
    """GAE written out: delta_t = x_t + gamma V(s'_t)(1 - term_t) - V(s_t); done cuts the sum."""
    value = [weight * s + bias for s in OBS]
    next_value = [weight * s + bias for s in NEXT_OBS]
    adv = [0.0] * len(OBS)
    running = 0.0
    for t in reversed(range(len(OBS))):
        done = TERMINATED[t] or TRUNCATED[t]
        delta = signal[t] + gamma * next_value[t] * (1.0 - TERMINATED[t]) - value[t]
        running = delta + gamma * lmbda * (1.0 - done) * running
        adv[t] = running
    target = [a + v for a, v in zip(adv, value)]
    return torch.tensor(adv).unsqueeze(-1), torch.tensor(target).unsqueeze(-1)


# --------------------------------------------------------------------------- tests
class TestCostGAE:
    def test_keys(self):
        gae = make_cost_gae(make_linear_critic("cost_value", 1.0, 0.0))
        keys = gae.tensor_keys
        assert (keys.reward, keys.value, keys.advantage, keys.value_target) == (
            "cost",
            "cost_value",
            "cost_advantage",
            "cost_value_target",
        )
        assert float(gae.gamma) == pytest.approx(0.99) and float(gae.lmbda) == pytest.approx(0.95)

    def test_matches_hand_computed_gae(self):
        td = make_trajectory()
        gae = make_cost_gae(make_linear_critic("cost_value", 2.0, 0.5), gamma=GAMMA, lmbda=LMBDA)
        with torch.no_grad():
            gae(td)
        expected_adv, expected_target = hand_gae(COST, 2.0, 0.5)
        torch.testing.assert_close(td["cost_advantage"], expected_adv)
        torch.testing.assert_close(td["cost_value_target"], expected_target)
        # the terminated step does not bootstrap, the truncated one does
        v = lambda s: 2.0 * s + 0.5  # noqa: E731
        assert td["cost_advantage"][2].item() == pytest.approx(COST[2] - v(OBS[2]))
        truncated_delta = COST[4] + GAMMA * v(NEXT_OBS[4]) - v(OBS[4])
        assert td["cost_advantage"][4].item() == pytest.approx(truncated_delta)
        assert "advantage" not in td.keys() and "value_target" not in td.keys()

    def test_reward_and_cost_gae_share_a_tensordict(self):
        td = make_trajectory()
        reward_gae = make_gae(make_linear_critic("state_value", 1.0, -0.3), gamma=GAMMA, lmbda=LMBDA)
        cost_gae = make_cost_gae(make_linear_critic("cost_value", 2.0, 0.5), gamma=GAMMA, lmbda=LMBDA)
        with torch.no_grad():
            reward_gae(td)
            snapshot = td.select("advantage", "value_target", "state_value").clone()
            cost_gae(td)
        # the cost GAE left every reward entry untouched ...
        for key in ("advantage", "value_target", "state_value"):
            torch.testing.assert_close(td[key], snapshot[key], rtol=0, atol=0)
        # ... and both are the hand-computed estimates of their own signal and critic
        adv_r, target_r = hand_gae(REWARD, 1.0, -0.3)
        adv_c, target_c = hand_gae(COST, 2.0, 0.5)
        torch.testing.assert_close(td["advantage"], adv_r)
        torch.testing.assert_close(td["value_target"], target_r)
        torch.testing.assert_close(td["cost_advantage"], adv_c)
        torch.testing.assert_close(td["cost_value_target"], target_c)
        torch.testing.assert_close(td["state_value"], torch.tensor(OBS).unsqueeze(-1) - 0.3)
        torch.testing.assert_close(td["cost_value"], 2.0 * torch.tensor(OBS).unsqueeze(-1) + 0.5)

    def test_batched_envs_match_single_env(self):
        single = make_trajectory()
        batched = torch.stack([make_trajectory(), make_trajectory()], 0)  # [2 envs, T]
        batched["next", "cost"][1] *= 3.0
        gae = make_cost_gae(make_linear_critic("cost_value", 2.0, 0.5), gamma=GAMMA, lmbda=LMBDA)
        with torch.no_grad():
            gae(single)
            gae(batched)
        torch.testing.assert_close(batched["cost_advantage"][0], single["cost_advantage"])
        adv3, _ = hand_gae([3.0 * c for c in COST], 2.0, 0.5)
        torch.testing.assert_close(batched["cost_advantage"][1], adv3)

    @staticmethod
    def grouped(td: TensorDict, n_agents: int = 2) -> TensorDict:
        """``td`` as a multi-agent group: every entry under ``"agents"``, agent k's cost times k + 1."""
        def group(source):
            entries = {key: source[key].unsqueeze(1).expand(-1, n_agents, 1).clone()
                       for key in source.keys() if key != "next"}
            return TensorDict(entries, batch_size=[source.shape[0], n_agents])

        out = TensorDict({"agents": group(td), "next": {"agents": group(td["next"])}}, batch_size=td.shape)
        out["next", "agents", "cost"] *= torch.arange(1.0, n_agents + 1).unsqueeze(-1)
        return out

    def test_nested_critic_keys_follow_its_group(self):
        critic = make_linear_critic("cost_value", 2.0, 0.5)
        nested = TensorDictModule(critic.module, in_keys=[("agents", "observation")],
                                  out_keys=[("agents", "cost_value")])
        gae = make_cost_gae(nested, gamma=GAMMA, lmbda=LMBDA)
        keys = gae.tensor_keys
        assert (keys.reward, keys.value, keys.advantage, keys.value_target, keys.done, keys.terminated) == (
            ("agents", "cost"), ("agents", "cost_value"), ("agents", "cost_advantage"),
            ("agents", "cost_value_target"), ("agents", "done"), ("agents", "terminated"))
        td = self.grouped(make_trajectory())
        with torch.no_grad():
            gae(td)
        for agent in range(2):
            expected_adv, expected_target = hand_gae([(agent + 1) * c for c in COST], 2.0, 0.5)
            torch.testing.assert_close(td["agents", "cost_advantage"][:, agent], expected_adv)
            torch.testing.assert_close(td["agents", "cost_value_target"][:, agent], expected_target)
        reward_gae = make_gae(TensorDictModule(critic.module, in_keys=[("agents", "observation")],
                                               out_keys=[("agents", "state_value")]))
        assert reward_gae.tensor_keys.reward == ("agents", "reward")
        assert reward_gae.tensor_keys.advantage == ("agents", "advantage")

    def test_explicit_keys_with_team_flags(self):
        nested = TensorDictModule(torch.nn.Linear(1, 1), in_keys=[("agents", "observation")],
                                  out_keys=[("agents", "c")])
        gae = make_cost_gae(nested, keys={"value": ("agents", "c"), "done": "done", "terminated": "terminated"})
        keys = gae.tensor_keys
        assert (keys.value, keys.reward, keys.done) == (("agents", "c"), ("agents", "cost"), "done")

    def test_top_level_keys_are_unchanged(self):
        keys = make_gae(make_linear_critic("state_value", 1.0, 0.0)).tensor_keys
        assert (keys.reward, keys.value, keys.advantage, keys.value_target, keys.done) == (
            "reward", "state_value", "advantage", "value_target", "done")
        keys = make_cost_gae(None).tensor_keys
        assert (keys.reward, keys.value, keys.done, keys.terminated) == ("cost", "cost_value", "done", "terminated")


class TestNormalizeAdvantages:
    def test_reward_standardised_cost_only_centred(self):
        gen = torch.Generator().manual_seed(0)
        adv = 3.0 * torch.randn(64, 1, generator=gen) + 2.0
        cadv = 5.0 * torch.randn(64, 1, generator=gen) + 7.0
        td = TensorDict({"advantage": adv.clone(), "cost_advantage": cadv.clone()}, [64])
        out = normalize_advantages(td)
        assert out is td  # in place
        torch.testing.assert_close(td["advantage"], (adv - adv.mean()) / (adv.std() + 1e-8))
        assert td["advantage"].mean().abs() < 1e-6
        assert td["advantage"].std().item() == pytest.approx(1.0, abs=1e-5)
        torch.testing.assert_close(td["cost_advantage"], cadv - cadv.mean())
        assert td["cost_advantage"].std().item() == pytest.approx(cadv.std().item(), rel=1e-5)

    def test_custom_and_skipped_keys(self):
        td = TensorDict({"a": torch.arange(4.0), ("agents", "c"): torch.arange(4.0)}, [4])
        normalize_advantages(td, reward_key=None, cost_key=("agents", "c"))
        torch.testing.assert_close(td["a"], torch.arange(4.0))
        torch.testing.assert_close(td["agents", "c"], torch.arange(4.0) - 1.5)

    def test_missing_key_raises(self):
        with pytest.raises(KeyError, match="cost_advantage"):
            normalize_advantages(TensorDict({"advantage": torch.zeros(3)}, [3]))
