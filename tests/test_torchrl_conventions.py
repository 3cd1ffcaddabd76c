"""TorchRL's conventions, as a TorchRL user relies on them, held by sg_torchrl's safe losses.

* A PPO-family loss computes the advantages it is not given (``ClipPPOLoss`` runs its value
  estimator): every first-order safe loss does so for both the reward and the cost advantage, on a
  raw ``env.rollout(...)``, and gets what the trainer gets from precomputing them (reward and cost
  GAE on the whole batch, SafePO's normalisation).
* ``loss.make_value_estimator(...)`` configures the estimators and ``loss.set_keys(...)`` remaps
  their keys, for the cost estimator as for the reward one.
* Losses that cannot compute an advantage say so (second-order ``TrustRegionLoss``, which has no
  critics; a batch without the cost signal).
"""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402
from torchrl.objectives.utils import ValueEstimators  # noqa: E402

import sg_torchrl  # noqa: E402
from sg_torchrl.objectives import (  # noqa: E402
    CUPLoss,
    FOCOPSLoss,
    LagrangeMultiplier,
    make_cost_gae,
    make_gae,
    NoMultiplier,
    normalize_advantages,
    PGLoss,
    PIDLagrangeMultiplier,
    PPOLagLoss,
    TrustRegionLoss,
)
from sg_torchrl.modules import make_actor_critics  # noqa: E402
from sg_torchrl.modules.mlp import write_values  # noqa: E402

ENV_ID = "SafetyHalfCheetahVelocity-v1"
NUM_ENVS, STEPS = 2, 12
ADVANTAGE_KEYS = ("advantage", "value_target", "cost_advantage", "cost_value_target")


@pytest.fixture(scope="module")
def rollout():
    """Modules and a raw rollout: 2 envs x 12 steps with episodes of 5 (truncations inside)."""
    env = sg_torchrl.make(ENV_ID, num_envs=NUM_ENVS, seed=0, max_episode_steps=5)
    torch.manual_seed(0)
    actor, critic, cost_critic = make_actor_critics(env.observation_dim, env.action_spec, [16, 16])
    with torch.no_grad():
        data = env.rollout(STEPS, actor, break_when_any_done=False)
    env.close()
    # A cost signal with some spread (the velocity cost is 0 while the random policy is slow).
    data["next", "cost"] = data["next", "cost"] + torch.rand_like(data["next", "cost"])
    # CUP's projection regularises towards the stage-one policy: the rollout policy stands in.
    data["stage1_loc"], data["stage1_scale"] = data["loc"] + 0.1, data["scale"] * 1.1
    assert data["next", "truncated"].any() and "action_log_prob" in data.keys()
    return (actor, critic, cost_critic), data


def precomputed(data, critic, cost_critic):
    """The way of a user's single-seed loop (``examples/vision.py``): values, both GAEs, SafePO's normalisation."""
    batch = data.clone()
    with torch.no_grad():
        write_values(batch, (critic, cost_critic), None)
        make_gae(None, gamma=0.99, lmbda=0.95)(batch)
        make_cost_gae(None, gamma=0.99, lmbda=0.95)(batch)
    flat = batch.reshape(-1)
    normalize_advantages(flat)
    return flat


LOSSES = {
    "ppo_lag": lambda a, c, cc: PPOLagLoss(a, c, cc, LagrangeMultiplier(cost_limit=25.0, init=0.7)),
    "cppo_pid": lambda a, c, cc: PPOLagLoss(a, c, cc, PIDLagrangeMultiplier(cost_limit=0.0)),
    "ppo": lambda a, c, cc: PPOLagLoss(a, c, cc, NoMultiplier()),
    "pg": lambda a, c, cc: PGLoss(a, c, cc),
    "focops": lambda a, c, cc: FOCOPSLoss(a, c, cc, LagrangeMultiplier(init=0.5, upper_bound=2.0)),
    "cup": lambda a, c, cc: CUPLoss(a, c, cc, LagrangeMultiplier(init=0.2)),
    "cup_reward_stage": lambda a, c, cc: CUPLoss(a, c, cc, LagrangeMultiplier()).reward_stage,
    "ppo_lag_not_functional": lambda a, c, cc: PPOLagLoss(a, c, cc, LagrangeMultiplier(init=0.7), functional=False),
}


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_loss_on_a_raw_rollout_computes_both_advantages(rollout, name):
    (actor, critic, cost_critic), data = rollout
    loss = LOSSES[name](actor, critic, cost_critic)
    raw = data.clone()
    out = loss(raw)
    assert not any(key in raw.keys() for key in ADVANTAGE_KEYS), "the input was written to"
    expected = loss(precomputed(data, critic, cost_critic))
    terms = [key for key in out.keys() if key.startswith("loss_")]
    assert "loss_objective" in terms and set(out.keys()) == set(expected.keys())
    # TorchRL's explained variances are per time step on an [N, T] batch (scalars on the flat one)
    compared = [key for key in out.keys() if "explained_variance" not in key]
    assert set(terms) <= set(compared) and {"kl_approx", "ESS", "mean_ratio"} <= set(compared)
    for key in out.keys():
        assert torch.isfinite(out[key]).all(), key
    for key in compared:
        torch.testing.assert_close(out[key], expected[key], msg=lambda m, key=key: f"{key}: {m}")
    total = sum(out[key] for key in terms)
    total.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())
    actor.zero_grad(), critic.zero_grad(), cost_critic.zero_grad()


def test_estimate_advantages_is_the_trainers_computation(rollout):
    (actor, critic, cost_critic), data = rollout
    loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
    mine = loss.estimate_advantages(data.clone()).reshape(-1)
    reference = precomputed(data, critic, cost_critic)
    for key in ADVANTAGE_KEYS:
        torch.testing.assert_close(mine[key], reference[key], msg=lambda m, key=key: f"{key}: {m}")
    flat = mine
    assert flat["advantage"].mean().abs() < 1e-5 and flat["advantage"].std().item() == pytest.approx(1.0, rel=1e-4)
    assert flat["cost_advantage"].mean().abs() < 1e-5 and flat["cost_advantage"].std().item() != pytest.approx(1.0)


def test_precomputed_advantages_are_used_as_given(rollout):
    """The trainer path: nothing is estimated when both advantages are in the batch."""
    (actor, critic, cost_critic), data = rollout
    loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.3))
    batch = precomputed(data, critic, cost_critic)
    batch["advantage"] = batch["advantage"] * 3.0  # not what an estimator would give
    out = loss(batch)
    assert loss._value_estimator is None and loss._cost_value_estimator is None
    again = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.3))(batch.exclude("next"))
    torch.testing.assert_close(out["loss_objective"], again["loss_objective"])


def test_only_the_missing_advantage_is_computed(rollout):
    (actor, critic, cost_critic), data = rollout
    loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.4))
    reference = precomputed(data, critic, cost_critic).reshape(data.shape)
    given = data.clone()
    given["advantage"] = torch.linspace(-1.0, 2.0, data.numel()).reshape(*data.shape, 1)
    given["value_target"] = reference["value_target"]
    out = loss(given)  # the cost advantage is computed and centred, the reward one used as given
    expected = reference.clone()
    expected["advantage"] = given["advantage"]
    for key in ("loss_objective", "loss_critic", "loss_cost_critic"):
        torch.testing.assert_close(out[key], loss(expected)[key])


def test_make_value_estimator_configures_both_estimators(rollout):
    (actor, critic, cost_critic), data = rollout
    loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.9, lmbda=0.8)
    for estimator in (loss.value_estimator, loss.cost_value_estimator):
        assert float(estimator.gamma) == pytest.approx(0.9) and float(estimator.lmbda) == pytest.approx(0.8)
    keys = loss.cost_value_estimator.tensor_keys
    assert (keys.reward, keys.value, keys.advantage, keys.value_target) == (
        "cost", "cost_value", "cost_advantage", "cost_value_target")
    mine = loss.estimate_advantages(data.clone())
    reference = data.clone()
    with torch.no_grad():
        make_gae(critic, gamma=0.9, lmbda=0.8)(reference)
        make_cost_gae(cost_critic, gamma=0.9, lmbda=0.8)(reference)
    normalize_advantages(reference)
    torch.testing.assert_close(mine["cost_advantage"], reference["cost_advantage"])
    torch.testing.assert_close(mine["advantage"], reference["advantage"])


def test_other_estimator_types_and_instances(rollout):
    (actor, critic, cost_critic), data = rollout
    from torchrl.objectives.value import GAE, TDLambdaEstimator

    loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
    loss.make_value_estimator(ValueEstimators.TDLambda, gamma=0.9, lmbda=0.5)
    assert isinstance(loss.cost_value_estimator, TDLambdaEstimator)
    assert float(loss.cost_value_estimator.gamma) == pytest.approx(0.9)
    assert loss.cost_value_estimator.tensor_keys.reward == "cost"
    assert torch.isfinite(loss(data.clone())["loss_cost_critic"])
    # an estimator instance replaces the reward one; the cost one is a GAE with its discounts
    loss.make_value_estimator(GAE(gamma=0.8, lmbda=0.7, value_network=critic))
    cost_estimator = loss.cost_value_estimator
    assert isinstance(cost_estimator, GAE) and cost_estimator.tensor_keys.value == "cost_value"
    assert (float(cost_estimator.gamma), float(cost_estimator.lmbda)) == pytest.approx((0.8, 0.7))


def test_set_keys_reaches_the_cost_estimator(rollout):
    (actor, critic, cost_critic), data = rollout
    loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
    loss.cost_value_estimator  # built first, remapped after
    loss.set_keys(cost="my_cost", cost_advantage="my_cadv", cost_value_target="my_ctarget")
    keys = loss.cost_value_estimator.tensor_keys
    assert (keys.reward, keys.advantage, keys.value_target) == ("my_cost", "my_cadv", "my_ctarget")
    renamed = data.clone()
    renamed["next", "my_cost"] = renamed["next"].pop("cost")
    out = loss(renamed)
    expected = loss(precomputed(data, critic, cost_critic).rename_key_("cost_advantage", "my_cadv")
                    .rename_key_("cost_value_target", "my_ctarget"))
    torch.testing.assert_close(out["loss_cost_critic"], expected["loss_cost_critic"])


def test_missing_cost_signal_says_what_is_missing(rollout):
    (actor, critic, cost_critic), data = rollout
    loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
    batch = data.clone()
    del batch["next", "cost"]
    with pytest.raises(KeyError, match=r"cost_advantage.*\('next', 'cost'\)"):
        loss(batch)


def test_trust_region_loss_names_the_missing_advantage(rollout):
    (actor, _, _), data = rollout
    loss = TrustRegionLoss(actor)
    with pytest.raises(KeyError, match="no critics"):
        loss(data.reshape(-1))
    batch = data.reshape(-1).clone()
    batch["advantage"] = torch.randn(batch.shape[0], 1)
    out = loss(batch)
    assert set(out.keys()) == {"loss_objective", "kl"} and torch.isfinite(out["loss_objective"])


def test_nested_cost_critic_in_a_multi_agent_rollout():
    """``make_cost_gae`` with a critic writing ``("agents", "cost_value")``, as a MARL user writes it."""
    env = sg_torchrl.make("Safety2x3HalfCheetahVelocity-v0", num_envs=2, seed=0, max_episode_steps=4)
    with torch.no_grad():
        data = env.rollout(7, break_when_any_done=False)
    env.close()
    data["next", "agents", "cost"] = torch.rand_like(data["next", "agents", "cost"])
    torch.manual_seed(0)
    obs_dim = data["agents", "observation"].shape[-1]
    from tensordict.nn import TensorDictModule

    critic = TensorDictModule(torch.nn.Linear(obs_dim, 1), in_keys=[("agents", "observation")],
                              out_keys=[("agents", "cost_value")])
    gae = make_cost_gae(critic, gamma=0.99, lmbda=0.95)
    keys = gae.tensor_keys
    assert keys.value == ("agents", "cost_value") and keys.reward == ("agents", "cost")
    with torch.no_grad():
        gae(data)
    assert data["agents", "cost_advantage"].shape == data["next", "agents", "cost"].shape
    # each agent's estimate is the single-agent GAE of its own cost and flags
    flat_critic = TensorDictModule(critic.module, in_keys=["observation"], out_keys=["cost_value"])
    for agent in range(data["agents"].shape[-1]):
        single = TensorDict({
            "observation": data["agents", "observation"][:, :, agent],
            "next": {name: data["next", "agents", name][:, :, agent]
                     for name in ("observation", "cost", "done", "terminated")},
        }, batch_size=data.shape)
        with torch.no_grad():
            make_cost_gae(flat_critic)(single)
        torch.testing.assert_close(data["agents", "cost_advantage"][:, :, agent], single["cost_advantage"])
        torch.testing.assert_close(data["agents", "cost_value_target"][:, :, agent], single["cost_value_target"])
