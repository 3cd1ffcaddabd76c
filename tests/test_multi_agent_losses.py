"""Tests of the multi-agent algorithms (MAPPO, HAPPO, MAPPO-Lag, MACPO) on synthetic TensorDicts.

The batches have the env's layout (group ``"agents"`` with batch ``[N, T, A]``, per-agent reward,
cost and done flags, a global ``"state"``), heterogeneous partitions padded to the largest agent.
"""

from __future__ import annotations

import copy
import math

import pytest
import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402
from torch import distributions as D  # noqa: E402
from torchrl.modules import PopArtValueNorm  # noqa: E402

from sg_torchrl.algorithms.manifest import MACPO_STEP_DEFAULTS  # noqa: E402
from sg_torchrl.modules import MultiAgentNetworks, make_multi_agent_networks  # noqa: E402
from sg_torchrl.modules.stacked_multi_agent import AgentRows  # noqa: E402
from sg_torchrl.objectives import gaussian_kl, NoMultiplier, PPOLagLoss  # noqa: E402
from sg_torchrl.objectives.multi_agent import (  # noqa: E402
    agent_view,
    AgentPPOLoss,
    MACPOStep,
    make_multi_agent_cost_gae,
    make_multi_agent_gae,
    MAPPOLagMultiplier,
)
from sg_torchrl.train.multi_agent_updates import HAPPOUpdate, MACPOUpdate, MAPPOLagUpdate, MAPPOUpdate  # noqa: E402

OBS, STATE, HIDDEN = 6, 9, (32, 32)
N, T = 4, 12
PARTITIONS = {"2 agents": [3, 3], "3 agents": [2, 2, 2], "2 agents, padded": [3, 2], "3 agents, padded": [1, 3, 2]}
UPDATES = (MAPPOUpdate, HAPPOUpdate, MAPPOLagUpdate, MACPOUpdate)
TEAM_METRICS = {
    "Loss/Loss_actor", "Loss/Loss_reward_critic", "Loss/Loss_cost_critic", "Misc/Entropy", "Misc/Ratio",
    "Misc/Reward_critic_norm", "Misc/Cost_critic_norm", "Train/KL", "Train/LagrangeMultiplier",
}


# =========================================================================== helpers
def make_nets(action_sizes: list[int], seed: int = 0) -> MultiAgentNetworks:
    torch.manual_seed(seed)
    return make_multi_agent_networks(OBS, action_sizes, STATE, hidden_sizes=HIDDEN)


def make_rollout(nets: MultiAgentNetworks, seed: int = 0, *, gae: bool = True) -> TensorDict:
    """A ``[N, T]`` rollout in the env's layout, actions sampled from ``nets.actor``, both GAEs run."""
    a = nets.n_agents
    gen = torch.Generator().manual_seed(seed)
    obs = torch.randn(N, T + 1, a, OBS, generator=gen)
    for i, size in enumerate(nets.action_sizes):  # smaller agents observe less (padding is zeros)
        obs[..., i, OBS - (max(nets.action_sizes) - size):] = 0.0
    state = torch.randn(N, T + 1, STATE, generator=gen)
    done = torch.zeros(N, T, a, 1, dtype=torch.bool)
    done[:, -1] = True
    done[0, T // 2] = True
    terminated = done.clone()
    terminated[:, -1] = False  # the rollout's end is a truncation
    team_reward = torch.randn(N, T, 1, 1, generator=gen).expand(N, T, a, 1).clone()
    td = TensorDict(
        {
            "agents": TensorDict({"observation": obs[:, :-1]}, [N, T, a]),
            "state": state[:, :-1],
            "next": TensorDict(
                {
                    "agents": TensorDict(
                        {
                            "observation": obs[:, 1:],
                            "reward": team_reward,
                            "cost": (torch.rand(N, T, a, 1, generator=gen) < 0.3).float(),
                            "done": done,
                            "terminated": terminated,
                            "truncated": done & ~terminated,
                        },
                        [N, T, a],
                    ),
                    "state": state[:, 1:],
                    "done": done[..., 0, :],
                    "terminated": terminated[..., 0, :],
                },
                [N, T],
            ),
        },
        [N, T],
    )
    with torch.no_grad():
        nets.actor(td)
        if gae:
            make_multi_agent_gae(nets.reward_critic)(td)
            make_multi_agent_cost_gae(nets.cost_critic)(td)
    return td


def agent_params(nets: MultiAgentNetworks, agent: int) -> torch.Tensor:
    modules = (nets.agent_actor(agent), nets.agent_critic(agent), nets.agent_cost_critic(agent))
    return torch.cat([p.detach().reshape(-1).clone() for m in modules for p in m.parameters()])


def hand_log_prob_per_dim(nets: MultiAgentNetworks, agent: int, view: TensorDict) -> torch.Tensor:
    """log N(a_d; mu_d, sigma_d) per real action dim, computed from the agent's raw MLP and head formula."""
    size = nets.action_sizes[agent]
    with torch.no_grad():
        mu = nets.policy.mlp.agent_networks[agent](view["observation"])[..., :size]
        sigma = torch.sigmoid(nets.policy.heads[agent].log_std) * 0.5
        return D.Normal(mu, sigma).log_prob(view["action"][..., :size])


# =========================================================================== networks
class TestNetworks:
    @pytest.mark.parametrize("sizes", PARTITIONS.values(), ids=PARTITIONS.keys())
    def test_group_shapes_padding_and_agent_modules(self, sizes):
        nets = make_nets(sizes)
        td = make_rollout(nets, gae=False)
        a, pad = len(sizes), max(sizes)
        group = td["agents"]
        assert group["action"].shape == (N, T, a, pad)
        assert group["action_log_prob"].shape == (N, T, a)
        with torch.no_grad():
            nets.reward_critic(td)
            nets.cost_critic(td)
        assert td["agents", "state_value"].shape == td["agents", "cost_value"].shape == (N, T, a, 1)
        for i, size in enumerate(sizes):
            # padding slots: constant loc 0, scale 1
            assert torch.all(group["loc"][..., i, size:] == 0) and torch.all(group["scale"][..., i, size:] == 1)
            assert torch.all(group["scale"][..., i, :size] < 0.5)
            # the agent's own modules reproduce the group outputs
            view = agent_view(td, i, keys=("observation", "action", "action_log_prob", "state_value"))
            actor = nets.agent_actor(i)
            with torch.no_grad():
                log_prob = actor.get_dist(view.select("observation")).log_prob(view["action"])
                value = nets.agent_critic(i)(view.select("state"))["state_value"]
            torch.testing.assert_close(log_prob, view["action_log_prob"])
            torch.testing.assert_close(value, view["state_value"])

    def test_agents_own_disjoint_parameters(self):
        nets = make_nets([3, 2, 1])
        ids = [{id(p) for p in (*nets.agent_actor(i).parameters(), *nets.agent_critic(i).parameters(),
                                *nets.agent_cost_critic(i).parameters())} for i in range(3)]
        assert all(ids[i].isdisjoint(ids[j]) for i in range(3) for j in range(i + 1, 3))
        assert set().union(*ids) == {id(p) for p in nets.parameters()}
        # each parameter appears once in the state dict (the wrappers are not registered twice)
        assert len(nets.state_dict()) == len(list(nets.parameters()))

    @pytest.mark.parametrize("batch", [(5,), (4, 3)])
    def test_group_forward_equals_torchrls_vmapped_forward(self, batch):
        # PerAgentMLP loops over its agents; MultiAgentMLP's own forward vmaps them: the same function.
        from torchrl.modules import MultiAgentMLP

        mlp = make_nets([3, 2, 1]).policy.mlp
        x = torch.randn(*batch, 3, OBS)
        out = mlp(x)
        torch.testing.assert_close(out, MultiAgentMLP.forward(mlp, x), rtol=1e-5, atol=1e-6)
        out[..., 1, :].sum().backward()  # agent 1's output depends on agent 1's parameters only
        grads = [any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())
                 for net in mlp.agent_networks]
        assert grads == [False, True, False]

    def test_padding_slots_do_not_change_the_ratio(self):
        nets = make_nets([3, 1])
        td = make_rollout(nets, gae=False)
        view = agent_view(td, 1, keys=("observation", "action", "action_log_prob"))
        actor = nets.agent_actor(1)
        with torch.no_grad():
            nets.policy.mlp.agent_networks[1][0].weight.add_(0.3)  # move agent 1's policy
            new = actor.get_dist(view.select("observation")).log_prob(view["action"])
        hand = hand_log_prob_per_dim(nets, 1, view).sum(-1)
        # the padded slots' log-density terms are the same before and after: they cancel in the ratio
        old_real = D.Normal(td["agents", "loc"][..., 1, :1], td["agents", "scale"][..., 1, :1]).log_prob(
            td["agents", "action"][..., 1, :1]).sum(-1).reshape(-1)
        torch.testing.assert_close(new - view["action_log_prob"], hand - old_real)


# =========================================================================== advantages
class TestAdvantages:
    def test_gae_shapes_and_per_agent_standardisation(self):
        nets = make_nets([3, 2, 1])
        td = make_rollout(nets)
        for key in ("advantage", "value_target", "cost_advantage", "cost_value_target"):
            assert td["agents", key].shape == (N, T, 3, 1)
            assert torch.isfinite(td["agents", key]).all()
        for key in ("advantage", "cost_advantage"):
            adv = td["agents", key]
            torch.testing.assert_close(adv.mean((0, 1, 3)), torch.zeros(3), atol=1e-5, rtol=0)
            torch.testing.assert_close(adv.std((0, 1, 3)), torch.ones(3), atol=1e-4, rtol=0)

    def test_cost_gae_reads_each_agents_cost(self):
        nets = make_nets([2, 2])
        td = make_rollout(nets, gae=False)
        td["next", "agents", "cost"][..., 0, :] = 0.0
        td["next", "agents", "cost"][..., 1, :] = 1.0
        with torch.no_grad():
            make_multi_agent_cost_gae(nets.cost_critic, standardize=False)(td)
        value = td["agents", "cost_value"]
        # target - value is the (unstandardised) advantage; agent 1 pays 1 per step, agent 0 nothing
        delta = td["agents", "cost_value_target"] - value
        torch.testing.assert_close(delta, td["agents", "cost_advantage"])
        assert (td["agents", "cost_value_target"][..., 1, :] > td["agents", "cost_value_target"][..., 0, :] + 0.5).all()


# =========================================================================== sequential update
class TestSequentialUpdate:
    def test_every_agent_once_per_round_in_random_orders(self):
        nets = make_nets([2, 2, 1, 2])
        td = make_rollout(nets)
        update = HAPPOUpdate(nets, epochs=1, generator=torch.Generator().manual_seed(3))
        orders = set()
        for _ in range(8):
            metrics = update(td, 10.0)
            stages = [int(metrics[f"Train/AgentOrder/agent{i}"]) for i in range(4)]
            assert sorted(stages) == [0, 1, 2, 3]
            orders.add(tuple(stages))
        assert len(orders) > 1
        fixed = HAPPOUpdate(nets, epochs=1, shuffle=False)(td, 10.0)
        assert [fixed[f"Train/AgentOrder/agent{i}"] for i in range(4)] == [0.0, 1.0, 2.0, 3.0]

    def test_each_stage_updates_only_that_agents_parameters(self):
        nets = make_nets([3, 2, 1])
        td = make_rollout(nets)
        update = HAPPOUpdate(nets, epochs=2, target_kl=None)
        inner = update._stage
        changed: list[tuple[int, list[bool]]] = []

        def spy(seeds, agents, fields, factor, costs):
            before = [agent_params(nets, j) for j in range(3)]
            out = inner(seeds, agents, fields, factor, costs)
            agent = int(agents[0])
            changed.append((agent, [not torch.equal(b, agent_params(nets, j)) for j, b in enumerate(before)]))
            return out

        update._stage = spy
        update(td, 10.0)
        assert sorted(agent for agent, _ in changed) == [0, 1, 2]
        for agent, flags in changed:
            assert flags == [j == agent for j in range(3)]

    def test_happo_factor_equals_hand_computed_product_of_first_agents_ratios(self):
        nets = make_nets([2, 2], seed=1)
        td = make_rollout(nets, seed=1)
        update = HAPPOUpdate(nets, shuffle=False, target_kl=None, actor_lr=3e-2)  # order 0, 1; a big step
        views = [agent_view(td, i) for i in range(2)]
        old_per_dim = hand_log_prob_per_dim(nets, 0, views[0])
        received: dict[int, torch.Tensor] = {}
        inner = update._stage

        def spy(seeds, agents, fields, factor, costs):
            agent = int(agents[0])
            received[agent] = factor[0].clone()
            if agent == 1:  # agent 1's loss (the LossModule view) with the factor it was given, by hand
                view = views[1].clone()
                view.set("factor", factor[0])
                loss = AgentPPOLoss(nets.agent_actor(1), nets.agent_critic(1), nets.agent_cost_critic(1),
                                    NoMultiplier(), functional=False)(view)
                r = (hand_log_prob_per_dim(nets, 1, view).sum(-1) - view["action_log_prob"]).exp()
                adv = view["advantage"].squeeze(-1)
                expected = -(factor[0] * torch.minimum(r * adv, r.clamp(0.8, 1.2) * adv)).mean()
                torch.testing.assert_close(loss["loss_objective"], expected)
            return inner(seeds, agents, fields, factor, costs)

        update._stage = spy
        update(td, 0.0)
        new_per_dim = hand_log_prob_per_dim(nets, 0, views[0])
        hand = (new_per_dim - old_per_dim).exp().prod(-1)  # product over agent 0's action dims
        torch.testing.assert_close(received[0], torch.ones(N * T))
        torch.testing.assert_close(received[1], hand)
        assert (hand - 1).abs().max() > 1e-2  # agent 0 really moved: the check is not trivial

    @pytest.mark.parametrize(("target_kl", "max_grad_norm", "minibatches"),
                             [(None, 10.0, 2), (0.005, 10.0, 2), (None, 0.05, 2), (0.005, 10.0, 1), (1e9, 10.0, 1)],
                             ids=["no KL stop", "KL stop", "every network clipped", "KL stop, whole batch",
                                  "whole batch, KL never stops"])
    def test_a_users_loop_over_agent_ppo_loss_is_the_rounds_update(self, target_kl, max_grad_norm, minibatches):
        """S = 1: each agent's AgentPPOLoss, torch.optim.Adam, the per-network clip, the multiplier step after every
        step, the KL stop and the factor by hand give what the seed-batched round gives, bit for bit (the recorded
        multi-agent runs were this loop; with one minibatch per pass, the round's steps take the actor evaluation of
        the KL pass before them)."""
        nets = make_nets([3, 2], seed=3)
        td = make_rollout(nets, seed=3)
        mine = copy.deepcopy(nets)
        update = MAPPOLagUpdate(nets, epochs=4, num_minibatches=minibatches, target_kl=target_kl, multiplier_init=0.1,
                                multiplier_lr=0.5, actor_lr=1e-2, max_grad_norm=max_grad_norm,
                                generator=torch.Generator().manual_seed(4))
        metrics = update(td, 40.0)

        generator = torch.Generator().manual_seed(4)
        order = torch.randperm(2, generator=generator).tolist()
        factor = torch.ones(N * T)
        multipliers = [MAPPOLagMultiplier(25.0, init=0.1, lr=0.5) for _ in range(2)]
        stops, clipped = {}, []
        for i in order:
            actor = mine.agent_actor(i)
            loss = AgentPPOLoss(actor, mine.agent_critic(i), mine.agent_cost_critic(i), multipliers[i],
                                value_norm=PopArtValueNorm(shape=1), functional=False)
            view = agent_view(td, i)
            view["factor"] = factor
            groups = [list(m.parameters()) for m in (actor, mine.agent_critic(i), mine.agent_cost_critic(i))]
            opt = torch.optim.Adam([{"params": groups[0], "lr": 1e-2}, {"params": groups[1] + groups[2], "lr": 5e-4}],
                                   eps=1e-5)
            with torch.no_grad():
                old = actor.get_dist(view.select("observation"))
                before = old.log_prob(view["action"])
            for epoch in range(1, 5):
                for index in torch.randperm(N * T, generator=generator).chunk(2) if minibatches == 2 else [...]:
                    out = loss(view[index])
                    opt.zero_grad()
                    sum(out[k] for k in ("loss_objective", "loss_critic", "loss_cost_critic", "loss_entropy")).backward()
                    norms = [torch.nn.utils.clip_grad_norm_(group, max_grad_norm) for group in groups]
                    clipped.append(all(norm > max_grad_norm for norm in norms))
                    opt.step()
                    multipliers[i].update(40.0, cost_surrogate=out["cost_surrogate"])
                with torch.no_grad():
                    new = actor.get_dist(view.select("observation"))
                    kl = gaussian_kl(old.mean, old.stddev, new.mean, new.stddev).mean().item()
                stops[i] = epoch
                if target_kl is not None and kl > target_kl:
                    break
            with torch.no_grad():
                factor = factor * (actor.get_dist(view.select("observation")).log_prob(view["action"]) - before).exp()
        for i in range(2):
            assert torch.equal(agent_params(nets, i), agent_params(mine, i))
            assert float(update.multipliers[i].value) == float(multipliers[i].value)
            assert metrics[f"Train/StopIter/agent{i}"] == stops[i]
        if target_kl is not None and target_kl < 1:
            assert min(stops.values()) < 4  # the stop fired: the check is not trivial
        assert all(clipped) == (max_grad_norm < 1)  # each network clipped on its own at every step

    @pytest.mark.parametrize(("minibatches", "evaluations"), [(1, 2 * (1 + 4)), (2, 2 * (1 + 4 + 4 * 2))])
    def test_the_round_evaluates_the_actor_once_per_pass_with_one_minibatch(self, monkeypatch, minibatches,
                                                                             evaluations):
        """Per stage: the old policy and each pass's KL evaluation; with one minibatch per pass the step after each
        of those takes it (4 epochs, 2 agents, no stop), with two every step evaluates its minibatch."""
        nets = make_nets([3, 2], seed=3)
        td = make_rollout(nets, seed=3)
        calls = []
        dist_params = AgentRows.dist_params
        monkeypatch.setattr(AgentRows, "dist_params", lambda rows, obs: calls.append(1) or dist_params(rows, obs))
        update = MAPPOLagUpdate(nets, epochs=4, num_minibatches=minibatches, target_kl=1e9,
                                generator=torch.Generator().manual_seed(4))
        metrics = update(td, 40.0)
        assert [metrics[f"Train/StopIter/agent{i}"] for i in range(2)] == [4, 4]
        assert len(calls) == evaluations

    def test_mappo_is_independent_per_agent_ppo(self):
        nets = make_nets([3, 2, 1], seed=2)
        td = make_rollout(nets, seed=2)
        options = dict(value_norm=False, target_kl=None, max_grad_norm=1e9)
        # two MAPPO rounds with different agent orders give the same networks ...
        results = []
        for seed, shuffle in ((0, False), (5, True)):
            copy_nets = copy.deepcopy(nets)
            update = MAPPOUpdate(copy_nets, shuffle=shuffle, generator=torch.Generator().manual_seed(seed), **options)
            factors = []
            inner = update._stage
            update._stage = lambda s, a, fields, f, c: factors.append(f) or inner(s, a, fields, f, c)
            update(td, 30.0)
            assert factors == [None] * 3  # no factor is kept
            assert "factor" not in update.loss.in_keys and not update.objective.weighted
            results.append([agent_params(copy_nets, i) for i in range(3)])
        for a, b in zip(*results):
            torch.testing.assert_close(a, b)
        # ... equal to single-agent PPO (PPOLagLoss with no multiplier) run on each agent's view alone
        for i in range(3):
            solo = copy.deepcopy(nets)
            loss = PPOLagLoss(solo.agent_actor(i), solo.agent_critic(i), solo.agent_cost_critic(i), NoMultiplier(),
                              entropy_coeff=0.01, critic_l2_coeff=None, functional=False)
            params = [*solo.agent_actor(i).parameters(), *solo.agent_critic(i).parameters(),
                      *solo.agent_cost_critic(i).parameters()]
            opt = torch.optim.Adam(params, lr=5e-4, eps=1e-5)
            view = agent_view(td, i)
            for _ in range(5):
                out = loss(view)
                opt.zero_grad()
                sum(out[k] for k in ("loss_objective", "loss_entropy", "loss_critic", "loss_cost_critic")).backward()
                opt.step()
            torch.testing.assert_close(agent_params(solo, i), results[0][i])


# =========================================================================== MAPPO-Lag
class TestMAPPOLag:
    def test_combined_advantage_is_factor_times_hybrid_advantage(self):
        nets = make_nets([3, 2])
        td = make_rollout(nets)
        multiplier = MAPPOLagMultiplier(init=0.5)
        loss = AgentPPOLoss(nets.agent_actor(1), nets.agent_critic(1), nets.agent_cost_critic(1), multiplier,
                            functional=False)
        view = agent_view(td, 1)
        view["factor"] = torch.rand(N * T) + 0.5
        combined = loss._combined_advantage(view)
        expected = view["factor"].unsqueeze(-1) * (view["advantage"] - 0.5 * view["cost_advantage"])
        torch.testing.assert_close(combined, expected)

    def test_multiplier_rule(self):
        m = MAPPOLagMultiplier(cost_limit=25.0, init=0.2, lr=0.5, gamma=0.99)
        assert not m.sum_norm
        # violated: lambda += lr * ((Jc - d)(1 - gamma) + E[r A_c])
        assert float(m.update(45.0, cost_surrogate=0.1)) == pytest.approx(0.2 + 0.5 * (20 * 0.01 + 0.1))
        # satisfied: it decreases, and is projected onto lambda >= 0
        assert float(m.update(5.0, cost_surrogate=-0.3)) == pytest.approx(0.35 + 0.5 * (-0.2 - 0.3))
        assert float(m.update(0.0, cost_surrogate=-5.0)) == 0.0
        safepo = MAPPOLagMultiplier(init=0.78, lr=1e-5)  # SafePO's config: practically constant
        for _ in range(100):
            safepo.update(100.0)
        assert float(safepo.value) == pytest.approx(0.78, abs=1e-3)

    def test_update_steps_each_agents_multiplier_after_every_minibatch_step(self):
        nets = make_nets([2, 3])
        td = make_rollout(nets)
        update = MAPPOLagUpdate(nets, epochs=1, multiplier_init=0.1, multiplier_lr=0.5, cost_limit=25.0)
        costs = torch.tensor([45.0, 5.0])  # per agent: one violates, one satisfies
        metrics = update(td, costs)
        for i in range(2):
            # one step, taken at the rollout policy (ratio 1): E[r A_c] = mean of the standardised A_c
            surrogate = float(agent_view(td, i)["cost_advantage"].mean())
            expected = max(0.0, 0.1 + 0.5 * ((float(costs[i]) - 25.0) * 0.01 + surrogate))
            assert float(update.multipliers[i].value) == pytest.approx(expected, abs=1e-6)
            assert metrics[f"Train/LagrangeMultiplier/agent{i}"] == pytest.approx(expected, abs=1e-6)
        assert metrics["Train/LagrangeMultiplier"] == pytest.approx(
            sum(float(m.value) for m in update.multipliers) / 2)


# =========================================================================== MACPO
def _policy_dists(nets: MultiAgentNetworks, td: TensorDict) -> list[tuple[torch.Tensor, torch.Tensor]]:
    out = []
    for i in range(nets.n_agents):
        view = agent_view(td, i, keys=("observation",), root_keys=())
        with torch.no_grad():
            dist = nets.agent_actor(i).get_dist(view)
        out.append((dist.mean, dist.stddev))
    return out


class TestMACPO:
    @pytest.mark.parametrize("sizes", [[3, 3], [1, 3, 2]], ids=["2 agents", "3 agents, padded"])
    @pytest.mark.parametrize("plain_line_search", [False, True], ids=["safepo steps", "full cpo steps"])
    @pytest.mark.parametrize("episode_cost", [5.0, 40.0], ids=["feasible", "infeasible"])
    def test_each_agents_step_respects_the_trust_region(self, sizes, plain_line_search, episode_cost):
        nets = make_nets(sizes, seed=3)
        td = make_rollout(nets, seed=3)
        options = dict(max_step_norm=None, initial_step_fraction=1.0) if plain_line_search else {}
        update = MACPOUpdate(nets, critic_epochs=1, **options)
        before = _policy_dists(nets, td)
        metrics = update(td, episode_cost)
        after = _policy_dists(nets, td)
        for i, ((loc0, scale0), (loc1, scale1)) in enumerate(zip(before, after)):
            kl = gaussian_kl(loc0, scale0, loc1, scale1).mean().item()
            assert kl <= 0.01 * (1 + 1e-5)
            assert kl == pytest.approx(metrics[f"Train/KL/agent{i}"], rel=1e-3, abs=1e-7)
            if plain_line_search and metrics[f"Misc/AcceptanceStep/agent{i}"] > 0:
                assert kl > 1e-4  # a real step, not a trivially small one

    def test_step_reduces_the_weighted_cost_surrogate_when_infeasible(self):
        nets = make_nets([3, 2], seed=4)
        td = make_rollout(nets, seed=4)
        view = agent_view(td, 1)
        factor = (torch.rand(N * T, generator=torch.Generator().manual_seed(0)) + 0.5).unsqueeze(-1)
        step = MACPOStep(nets.agent_actor(1), max_step_norm=None, initial_step_fraction=1.0)
        actor = nets.agent_actor(1)

        def surrogates():
            with torch.no_grad():
                r = (actor.get_dist(view.select("observation")).log_prob(view["action"]) - view["action_log_prob"]).exp()
            return [float((r * factor.squeeze(-1) * view[k].squeeze(-1)).mean()) for k in ("advantage", "cost_advantage")]

        reward0, cost0 = surrogates()
        c = (200.0 - 25.0) * (1 - 0.99)  # far above the limit
        metrics = step.step(view, factor * view["advantage"], factor * view["cost_advantage"], c)
        reward1, cost1 = surrogates()
        assert metrics["Misc/CPOCase"] in (0.0, 1.0)  # infeasible
        assert metrics["Misc/AcceptanceStep"] > 0
        assert cost1 < cost0
        assert metrics["Loss/Loss_actor"] == pytest.approx(-reward0, abs=1e-6)  # the factor-weighted surrogate

    def test_step_direction_is_capped_and_scaled(self):
        nets = make_nets([2, 2], seed=5)
        td = make_rollout(nets, seed=5)
        view = agent_view(td, 0)
        step = MACPOStep(nets.agent_actor(0), max_step_norm=1e-3, initial_step_fraction=0.1)
        metrics = step.step(view, view["advantage"], view["cost_advantage"], -0.2)
        assert metrics["Misc/StepNormRaw"] > 1e-3
        assert metrics["Misc/AcceptanceStep"] == 1.0
        assert metrics["Misc/FinalStepNorm"] == pytest.approx(0.1 * 1e-3, rel=1e-4)

    def test_step_defaults_are_the_manifests(self):
        step = MACPOStep(make_nets([2, 2]).agent_actor(0))
        assert {name: getattr(step, name) for name in MACPO_STEP_DEFAULTS} == dict(MACPO_STEP_DEFAULTS)
        assert MACPO_STEP_DEFAULTS["max_step_norm"] == 0.5 and MACPO_STEP_DEFAULTS["initial_step_fraction"] == 0.1

    @pytest.mark.parametrize("name, value", [("max_step_norm", 0.0), ("initial_step_fraction", 1.5),
                                             ("target_kl", 0.0), ("step_fraction", 1.0), ("cg_iters", 0),
                                             ("cg_damping", -1.0)])
    def test_round_refuses_bad_step_options_when_built(self, name, value):
        with pytest.raises(ValueError, match=name):
            MACPOUpdate(make_nets([2, 2]), **{name: value})


# =========================================================================== all algorithms
class TestRounds:
    @pytest.mark.parametrize("sizes", PARTITIONS.values(), ids=PARTITIONS.keys())
    def test_agent_losses_have_finite_gradients(self, sizes):
        nets = make_nets(sizes)
        td = make_rollout(nets)
        for i in range(len(sizes)):
            loss = AgentPPOLoss(nets.agent_actor(i), nets.agent_critic(i), nets.agent_cost_critic(i),
                                MAPPOLagMultiplier(init=0.3), functional=False)
            view = agent_view(td, i)
            view["factor"] = torch.rand(N * T) + 0.5
            out = loss(view)
            total = out["loss_objective"] + out["loss_entropy"] + out["loss_critic"] + out["loss_cost_critic"]
            nets.zero_grad()
            total.backward()
            own = [*nets.agent_actor(i).parameters(), *nets.agent_critic(i).parameters(),
                   *nets.agent_cost_critic(i).parameters()]
            assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in own)
            assert any(p.grad.abs().sum() > 0 for p in nets.agent_actor(i).parameters())
            others = {id(p) for p in own}
            assert all(p.grad is None for p in nets.parameters() if id(p) not in others)
            # the padding slots of the agent's output layer get no gradient
            size = sizes[i]
            last = nets.policy.mlp.agent_networks[i][-1]
            assert torch.all(last.weight.grad[size:] == 0) and torch.all(last.bias.grad[size:] == 0)

    @pytest.mark.parametrize("update_class", UPDATES, ids=lambda c: c.__name__)
    @pytest.mark.parametrize("sizes", [[3, 3], [1, 3, 2]], ids=["2 agents", "3 agents, padded"])
    def test_round_runs_and_reports_safepo_metrics(self, update_class, sizes):
        nets = make_nets(sizes)
        td = make_rollout(nets)
        update = update_class(nets, generator=torch.Generator().manual_seed(1))
        metrics = update(td, 30.0)
        assert TEAM_METRICS <= metrics.keys()
        for i in range(len(sizes)):
            assert f"Loss/Loss_actor/agent{i}" in metrics and f"Train/AgentOrder/agent{i}" in metrics
        assert sorted(metrics[f"Train/AgentOrder/agent{i}"] for i in range(len(sizes))) == list(range(len(sizes)))
        assert all(math.isfinite(v) for v in metrics.values())
        assert all(torch.isfinite(p).all() for p in nets.parameters())

    def test_state_dict_round_trip(self):
        nets = make_nets([2, 3])
        td = make_rollout(nets)
        update = MAPPOLagUpdate(nets, generator=torch.Generator().manual_seed(7))
        update(td, 40.0)
        state = copy.deepcopy(update.state_dict())
        twin_nets = copy.deepcopy(nets)
        twin = MAPPOLagUpdate(twin_nets)
        twin.load_state_dict(state)
        update(td, 40.0)
        twin(td, 40.0)
        for i in range(2):
            torch.testing.assert_close(agent_params(nets, i), agent_params(twin_nets, i))
            assert float(update.multipliers[i].value) == float(twin.multipliers[i].value)


# =========================================================================== with the env
ENV_IDS = ["Safety2x3HalfCheetahVelocity-v0", "Safety9|8HumanoidVelocity-v0"]


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_rounds_on_a_multi_agent_env_rollout(env_id):
    """The env's own layout (heterogeneous 9|8 padding included) feeds the networks, GAEs and every round."""
    import sg_torchrl

    if env_id not in sg_torchrl.list_envs():
        pytest.skip(f"{env_id} is not registered")
    env = sg_torchrl.make(env_id, num_envs=3, seed=0)
    torch.manual_seed(0)
    nets = make_multi_agent_networks(env.observation_spec["agents", "observation"].shape[-1], env.action_sizes,
                                     env.observation_spec["state"].shape[-1], hidden_sizes=HIDDEN)
    with torch.no_grad():
        td = env.rollout(16, nets.actor, break_when_any_done=False)
        make_multi_agent_gae(nets.reward_critic)(td)
        make_multi_agent_cost_gae(nets.cost_critic)(td)
    assert td["agents", "advantage"].shape == (3, 16, len(env.action_sizes), 1)
    for update_class in UPDATES:
        metrics = update_class(nets)(td, 30.0)
        assert TEAM_METRICS <= metrics.keys() and all(math.isfinite(v) for v in metrics.values())


def test_seed_batched_objective_rejects_what_the_round_lacks():
    # The multi-agent round's form of AgentPPOLoss names every option it would silently drop.
    nets = make_nets([3, 2])
    triple = (nets.agent_actor(0), nets.agent_critic(0), nets.agent_cost_critic(0))
    with pytest.raises(ValueError, match="multi-agent round does not implement: clip_value"):
        AgentPPOLoss(*triple, NoMultiplier(), clip_value=0.2, functional=False).seed_batched_objective()
    with pytest.raises(ValueError, match="critics_only"):
        AgentPPOLoss(*triple, NoMultiplier(), functional=False).seed_batched_objective(critics_only=True)
    assert AgentPPOLoss(*triple, NoMultiplier(), functional=False).seed_batched_objective().entropy_coeff == pytest.approx(0.01)
