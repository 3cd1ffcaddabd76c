"""The off-policy engine's stacked actions are the TorchRL actor's, bit for bit.

Collection, the actor's gradient steps (:class:`~sg_torchrl.modules.off_policy.StackedOffPolicyNets`) and an
exported or evaluated actor (the TorchRL modules of :func:`~sg_torchrl.modules.off_policy.make_off_policy_networks`)
must act alike to the last bit, for [-1, 1] bounds (where ``TanhModule`` still rescales) and for others:

* TD3's and DDPG's deterministic action (``TanhModule``), SAC's squashed mean (``TanhNormal``'s deterministic
  sample), every seed of a stack against its own TorchRL actor (``torch.equal``);
* SAC's reparameterised sample and its log-probability against ``rsample_and_log_prob`` of the actor's
  ``TanhNormal`` on the same standard-normal draw;
* the gradients of both with respect to the actor's weights (the actor's steps), bit for bit as well.
"""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules.distributions.utils import rsample_and_log_prob

from sg_torchrl.modules.off_policy import StackedOffPolicyNets, make_off_policy_networks
from sg_torchrl.train.off_policy import off_policy_network_options

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

OBS, HIDDEN, SEEDS = 7, [32, 32], 3
BOUNDS = {"unit": Bounded(-torch.ones(3), torch.ones(3), (3,)),
          "other": Bounded(torch.tensor([-0.4, -2.0, 0.0]), torch.tensor([0.4, 1.0, 3.0]), (3,))}


def _gradient_row(nets: StackedOffPolicyNets, actor) -> torch.Tensor:
    """``actor``'s parameter gradients laid out as a stacked actor row."""
    gradients, row = copy.deepcopy(actor), torch.zeros(nets.actor_layout.numel)
    for into, parameter in zip(gradients.parameters(), actor.parameters(), strict=True):
        into.data.copy_(parameter.grad)
    nets.actor_layout.load(row, gradients)
    return row


def _stack(algo: str, spec: Bounded):
    options = off_policy_network_options(algo)
    singles = []
    for seed in range(SEEDS):
        torch.manual_seed(seed)
        singles.append(make_off_policy_networks(OBS, spec, HIDDEN, **options))
    nets = StackedOffPolicyNets.from_single(singles, OBS, spec, HIDDEN, stochastic=options["stochastic"])
    scales = torch.logspace(0, 3, 400).view(400, 1)  # up to 1000: some actions saturate the tanh
    obs = torch.randn(SEEDS, 400, OBS, generator=torch.Generator().manual_seed(3)) * scales
    return nets, [actor for actor, _, _ in singles], obs


@pytest.mark.parametrize("bounds", sorted(BOUNDS))
@pytest.mark.parametrize("algo", ["td3", "ddpg", "sac_lag"])
def test_the_stacked_deterministic_action_is_the_torchrl_actors(algo, bounds):
    nets, actors, obs = _stack(algo, BOUNDS[bounds])
    stacked = nets.action(nets.actor, obs)
    stacked.pow(2).sum().backward()  # the actor's step differentiates this action (TD3, DDPG)
    for seed, actor in enumerate(actors):
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            expected = actor(TensorDict({"observation": obs[seed]}, batch_size=[obs.shape[1]]))["action"]
        assert torch.equal(stacked[seed], expected), (seed, (stacked[seed] - expected).abs().max())
        expected.pow(2).sum().backward()
        assert torch.equal(nets.actor.grad[seed], _gradient_row(nets, actor))
    low, high = BOUNDS[bounds].space.low, BOUNDS[bounds].space.high
    assert ((stacked >= low) & (stacked <= high)).all() and (torch.minimum(stacked - low, high - stacked) < 1e-5).any()  # saturated


@pytest.mark.parametrize("bounds", sorted(BOUNDS))
def test_the_stacked_sac_sample_is_the_tanh_normals(bounds, monkeypatch):
    nets, actors, obs = _stack("sac_lag", BOUNDS[bounds])
    noise = torch.randn(SEEDS, obs.shape[1], nets.action_dim, generator=torch.Generator().manual_seed(4)) * 2
    action, log_prob = nets.sample(nets.actor, obs, noise)
    (action.sum() + log_prob.sum()).backward()
    for seed, actor in enumerate(actors):
        # the Gaussian's standard-normal draw (``Normal.rsample``) is this seed's noise
        monkeypatch.setattr(torch.distributions.normal, "_standard_normal",
                            lambda shape, dtype, device, draw=noise[seed]: draw.to(dtype=dtype, device=device))
        dist = actor.get_dist(TensorDict({"observation": obs[seed]}, batch_size=[obs.shape[1]]))
        expected, expected_log_prob = rsample_and_log_prob(dist)
        assert torch.equal(action[seed], expected), (action[seed] - expected).abs().max()
        assert torch.equal(log_prob[seed], expected_log_prob), (log_prob[seed] - expected_log_prob).abs().max()
        # and the actor's step follows the same function: the same gradient with respect to its weights
        actor.zero_grad()
        (expected.sum() + expected_log_prob.sum()).backward()
        assert torch.equal(nets.actor.grad[seed], _gradient_row(nets, actor))
