"""The second-order seed-group update (``TrustRegionGroupUpdate``) against SafePO's single-seed epoch.

``tests/test_seed_group.py`` checks that seed s of a group follows the group of s alone, end to end
(CPO, TRPO-Lag, PCPO among the algorithms). This file checks the update itself against the
single-seed trainer's, on synthetic batches of two seeds with different costs (one above the limit,
one below, so the multipliers and CPO / PCPO's violations differ per seed):

* **every second-order algorithm**, each seed of the group against its own single-seed epoch written
  with the public pieces (:func:`single_update`: the row's trust-region step class on the TorchRL
  actor, then the loss's ``critic_losses`` in minibatch passes of ``Adam`` over the critics alone, the
  same minibatch generator seed): the same metric names in the same
  order, values to rtol 1e-4 / atol 1e-6 (float32: the stacked pass sums in another order, which
  conjugate gradient amplifies, as in ``tests/test_stacked_trust_region.py``), discrete ones (accepted
  trial, CPO case, critic passes) equal; the actor to rtol 1e-4 / atol 1e-6 and the critics after their
  passes to atol 1e-5 (Adam lifts 1e-7 rounding differences on near-zero gradient entries, as in the
  first-order tests). The actor's Adam group is never stepped;
* **a frozen seed** (its actor row non-finite) is neither moved nor computed on, its critics and Adam
  rows stay bit for bit, its step metrics are NaN, and the live seeds move as they do in a group
  where every seed is live (rtol 1e-5: a two-row stack instead of three);
* **divergence inside the step** (RCPO, whose natural step has no line search to refuse a non-finite
  candidate): the seed is flagged and put back bit for bit; the other seed moves bit for bit as in a
  clean run;
* **compiled** (``compile=True``): a CPO group compiles its critic passes (the fused critics-only step
  and the masked Adam; the trust-region step stays eager) without error and reuses the graphs after
  the first epoch; the first epoch's step metrics equal the eager group's bit for bit (the step comes
  before any compiled pass) and its critic losses to rtol 1e-4;
* ``keep_freed_memory`` (what ``OnPolicyGroupTrainer`` applies at start-up) acts on Linux with glibc only.
"""

from __future__ import annotations

import copy
import math

import pytest
import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402
from torch._dynamo.utils import counters  # noqa: E402
from torchrl.data import Bounded  # noqa: E402

from sg_torchrl.algorithms import manifest  # noqa: E402
from sg_torchrl.train import ALGORITHMS, OnPolicyGroupTrainer, TrainConfig  # noqa: E402
from sg_torchrl.train.algorithms import _NO_LINE_SEARCH, TRUST_REGION_STEPS, _trust_region_options  # noqa: E402
from sg_torchrl.train.fused import FusedFirstOrderStep, SeedShuffler, multiplier_values  # noqa: E402
from sg_torchrl.train.group_updates import GroupParts  # noqa: E402
from sg_torchrl.modules import StackedActorCritic, make_actor_critics  # noqa: E402

OBS, ACT, HIDDEN, N = 5, 2, [16, 16], 300
SPEC = Bounded(-1.0, 1.0, shape=(ACT,))
SEEDS, COSTS = (3, 11), (40.0, 10.0)  # episode costs against the limit 25: one seed above it, one below
WARM_UP_COST = 50.0  # every multiplier's first epoch: all grow, then each follows its seed's cost
SECOND_ORDER = ("npg", "trpo", "trpo_lag", "rcpo", "cpo", "pcpo")
DISCRETE = ("Misc/AcceptanceStep", "Misc/CPOCase", "Train/StopIter")


def config(algo: str, **options) -> TrainConfig:
    return TrainConfig(algo=algo, update_iters=3, minibatch_size=128, eval_episodes=0, wandb="disabled",
                       progress=False, **options)


def networks(seed: int):
    torch.manual_seed(seed)
    return make_actor_critics(OBS, SPEC, HIDDEN)


def batch(seed: int, actor) -> TensorDict:
    """A collected-like flat batch: advantages tied to the actions, so both surrogates have slopes."""
    gen = torch.Generator().manual_seed(1000 + seed)
    with torch.no_grad():
        data = actor(TensorDict(observation=torch.randn(N, OBS, generator=gen), batch_size=[N]))
    noise = (data["action"] - data["loc"]) / data["scale"]
    adv = noise[:, :1] + 0.3 * torch.randn(N, 1, generator=gen)
    cost_adv = noise[:, :1] + noise[:, 1:] + 0.3 * torch.randn(N, 1, generator=gen)
    data["advantage"] = (adv - adv.mean()) / (adv.std() + 1e-8)
    data["cost_advantage"] = cost_adv - cost_adv.mean()
    data["value_target"] = torch.randn(N, 1, generator=gen)
    data["cost_value_target"] = 3.0 * torch.rand(N, 1, generator=gen)
    return data.select("observation", "action", "action_log_prob", "loc", "scale", "advantage", "cost_advantage",
                       "value_target", "cost_value_target")


def flat(modules) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for module in modules for p in module.parameters()])


def single_update(algo: str, index: int, nets, data: TensorDict, **options):
    """Seed ``index`` through SafePO's single-seed second-order epoch: (metrics, networks).

    The row's trust-region step (the algorithm table's step class and options) on the TorchRL actor with
    the multiplier's advantage, then ``update_iters`` shuffled passes of ``loss.critic_losses`` with Adam
    over the critics, their gradients clipped together (SafePO's critic loop, no early stop).
    """
    cfg, row = config(algo, **options), ALGORITHMS[algo]
    actor, critic, cost_critic = copy.deepcopy(nets)
    multiplier = row.make_multiplier(cfg)
    for cost in (WARM_UP_COST, COSTS[index]):
        multiplier.update(cost)
    loss = row.make_loss(actor, critic, cost_critic, multiplier, cfg)
    optimizer = torch.optim.Adam([{"params": [*critic.parameters(), *cost_critic.parameters()],
                                   "lr": cfg.critic_lr}], fused=True)
    entry = manifest.get(algo)
    step = TRUST_REGION_STEPS[entry.update](actor, **_trust_region_options(cfg, entry.update not in _NO_LINE_SEARCH),
                                            **cfg.keyword_options(entry.step_options))
    data = data.clone()
    advantage = multiplier.combine(data["advantage"], data["cost_advantage"])
    metrics = dict(step.step(data, advantage, data["cost_advantage"], multiplier.violation(COSTS[index])))
    terms = ("loss_critic", "loss_cost_critic")
    inputs = data.select(*(key for key in loss.in_keys if key in data.keys()))
    params, generator = [*critic.parameters(), *cost_critic.parameters()], torch.Generator().manual_seed(SEEDS[index])
    sums, steps = dict.fromkeys(terms, 0.0), 0
    for _ in range(cfg.update_iters):  # SafePO's critic loop: a permutation per pass cut into minibatches
        permutation = torch.randperm(len(inputs), generator=generator)
        for start in range(0, len(inputs), cfg.minibatch_size):
            out = loss.critic_losses(inputs[permutation[start : start + cfg.minibatch_size]])
            optimizer.zero_grad(set_to_none=True)
            (out[terms[0]] + out[terms[1]]).backward()
            torch.nn.utils.clip_grad_norm_(params, cfg.max_grad_norm, foreach=True)
            optimizer.step()
            sums = {name: total + out[name].item() for name, total in sums.items()}
            steps += 1
    means = {name: total / steps for name, total in sums.items()}
    metrics.update({"Train/StopIter": cfg.update_iters, "Loss/Loss_reward_critic": means["loss_critic"],
                    "Loss/Loss_cost_critic": means["loss_cost_critic"]})
    return metrics, (actor, critic, cost_critic)


def group_update(algo: str, nets, costs=COSTS, seeds=SEEDS, **options):
    """The group's update, built as ``OnPolicyGroupTrainer`` builds it; returns (update, stacked data, lam, violation)."""
    cfg, row = config(algo, **options), ALGORITHMS[algo]
    model = StackedActorCritic.from_single([copy.deepcopy(triple) for triple in nets])
    optimizer = FusedFirstOrderStep.make_optimizer(model, 0.0, cfg.critic_lr, max_grad_norm=cfg.max_grad_norm)
    parts = GroupParts(model, optimizer, SeedShuffler(seeds), passes=cfg.update_iters,
                       minibatch_size=cfg.minibatch_size, target_kl=cfg.target_kl)
    multipliers = [row.make_multiplier(cfg) for _ in seeds]
    for multiplier, cost in zip(multipliers, costs):
        for value in (WARM_UP_COST, cost):
            multiplier.update(value)
    loss = row.make_loss(*copy.deepcopy(nets[0]), multipliers[0], cfg)
    violation = torch.tensor([m.violation(cost) for m, cost in zip(multipliers, costs)], dtype=torch.float64)
    return row.make_group_update(parts, loss, cfg), multiplier_values(multipliers), violation


def stacked(batches) -> dict[str, torch.Tensor]:
    data = {key: torch.stack([b[key] for b in batches]) for key in batches[0].keys()}
    data["action_log_prob"] = data["action_log_prob"].unsqueeze(-1)
    return data


def seed_rows(update, seed: int) -> list[torch.Tensor]:
    """Seed ``seed``'s parameters, Adam moments and step counts, as copies."""
    out = [t[seed].clone() for t in update.parts.model.flat_groups]
    for state in update.parts.optimizer.state:
        out += [state["step"][seed].clone(), *(t[seed].clone() for t in state["exp_avg"] + state["exp_avg_sq"])]
    return out


#: Rows with a step option set away from its default (``--pcpo-hx-direction true``: SafePO's PCPO reward step).
STEP_OPTIONS = [(algo, {}) for algo in SECOND_ORDER] + [("pcpo", {"pcpo_hx_direction": True})]


@pytest.mark.parametrize("algo, options", STEP_OPTIONS,
                         ids=[algo + "".join(f"-{name}" for name in options) for algo, options in STEP_OPTIONS])
def test_each_seed_of_the_group_update_is_its_single_seed_update(algo, options):
    nets = [networks(seed) for seed in SEEDS]
    batches = [batch(seed, triple[0]) for seed, triple in zip(SEEDS, nets)]
    update, lam, violation = group_update(algo, nets, **options)
    result = update(stacked(batches), lam, violation, torch.ones(len(SEEDS), dtype=torch.bool))
    assert not result.diverged.any()
    model = update.parts.model
    for index in range(len(SEEDS)):
        expected, single_nets = single_update(algo, index, nets[index], batches[index], **options)
        assert list(result.metrics) == list(expected)  # the single-seed names, in its order
        for name, value in expected.items():
            got = result.metrics[name][index].item()
            if name in DISCRETE:
                assert got == value, name
            else:
                assert got == pytest.approx(value, rel=1e-4, abs=1e-6), name
        exported = model.export_seed(index, SPEC)
        torch.testing.assert_close(flat(exported[:1]), flat(single_nets[:1]), rtol=1e-4, atol=1e-6)
        torch.testing.assert_close(flat(exported[1:]), flat(single_nets[1:]), rtol=0, atol=1e-5)
    assert not update.parts.optimizer.state[0]["step"].any()  # the actor's Adam group never moved
    if algo in ("trpo_lag", "rcpo"):  # the Lagrangian advantage: each seed its own multiplier
        assert lam[0] > lam[1] > 0
    if algo == "cpo":  # one seed infeasible, one feasible: each its own CPO case from its own violation
        assert result.metrics["Misc/CPOCase"][0] != result.metrics["Misc/CPOCase"][1]


def test_pcpo_hx_direction_takes_another_step_and_only_pcpo_reads_it():
    nets = [networks(seed) for seed in SEEDS]
    data = stacked([batch(seed, triple[0]) for seed, triple in zip(SEEDS, nets)])
    actors = []
    for options in ({}, {"pcpo_hx_direction": True}):
        update, lam, violation = group_update("pcpo", nets, **options)
        update(data, lam, violation, torch.ones(len(SEEDS), dtype=torch.bool))
        actors.append(update.parts.model.flat_actor.clone())
    assert not torch.allclose(actors[0], actors[1], rtol=1e-3, atol=1e-5)
    with pytest.raises(ValueError, match="pcpo_hx_direction is an option of pcpo, not of 'cpo'"):
        config("cpo", pcpo_hx_direction=True).validate()


def test_a_frozen_seed_is_not_touched_and_the_live_ones_move_as_in_a_full_group():
    seeds, costs = (3, 5, 11), (40.0, 30.0, 10.0)
    nets = [networks(seed) for seed in seeds]
    data = stacked([batch(seed, triple[0]) for seed, triple in zip(seeds, nets)])
    full, lam, violation = group_update("cpo", nets, costs, seeds)
    full(data, lam, violation, torch.ones(3, dtype=torch.bool))

    frozen, lam, violation = group_update("cpo", nets, costs, seeds)
    with torch.no_grad():
        frozen.parts.model.flat_actor[1] = math.nan  # as a seed found non-finite at the start of an epoch
    before = seed_rows(frozen, 1)
    result = frozen(data, lam, violation, torch.tensor([True, False, True]))
    assert not result.diverged.any()
    after = seed_rows(frozen, 1)
    assert after[0].isnan().all()
    for mine, saved in zip(after[1:], before[1:]):
        assert torch.equal(mine, saved)
    assert math.isnan(result.metrics["Misc/xHx"][1]) and result.metrics["Train/StopIter"].tolist() == [3, 0, 3]
    for seed in (0, 2):
        for mine, theirs in zip(seed_rows(frozen, seed), seed_rows(full, seed)):
            torch.testing.assert_close(mine, theirs, rtol=1e-5, atol=1e-7)


def test_a_seed_whose_trust_region_step_turns_non_finite_is_put_back_and_flagged():
    nets = [networks(seed) for seed in SEEDS]
    batches = [batch(seed, triple[0]) for seed, triple in zip(SEEDS, nets)]
    clean, lam, violation = group_update("rcpo", nets)
    clean(stacked(batches), lam, violation, torch.ones(2, dtype=torch.bool))

    broken, lam, violation = group_update("rcpo", nets)
    data = stacked(batches)
    data["advantage"][0, 7] = math.nan  # seed 0's gradient, hence its natural step, turns NaN
    before = seed_rows(broken, 0)
    result = broken(data, lam, violation, torch.ones(2, dtype=torch.bool))
    assert result.diverged.tolist() == [True, False]
    assert result.metrics["Train/StopIter"].tolist() == [0, 3]  # no critic pass for a NaN actor
    for restored, saved in zip(seed_rows(broken, 0), before):
        assert torch.equal(restored, saved)
    for mine, alone in zip(seed_rows(broken, 1), seed_rows(clean, 1)):
        assert torch.equal(mine, alone)


def test_keep_freed_memory_applies_on_linux_glibc_only(monkeypatch):
    import platform
    import sys

    from sg_torchrl.train import memory

    on_glibc = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    assert memory.keep_freed_memory() is on_glibc
    assert memory.keep_freed_memory() is on_glibc  # idempotent (every OnPolicyGroupTrainer calls it)
    monkeypatch.setattr(memory.sys, "platform", "darwin")
    assert memory.keep_freed_memory() is False


def test_a_compiled_group_compiles_its_critic_passes_once(tmp_path):
    def group(name: str, compile: bool) -> OnPolicyGroupTrainer:
        return OnPolicyGroupTrainer(TrainConfig(
            algo="cpo", env_id="SafetyHalfCheetahVelocity-v1", env_options={"max_episode_steps": 100}, num_envs=2,
            steps_per_epoch=400, total_steps=1200, update_iters=2, cost_limit=0.0, eval_episodes=0, wandb="disabled",
            progress=False, output_dir=str(tmp_path / name), seeds=[0, 1], compile=compile))

    compiled, eager = group("compiled", True), group("eager", False)
    assert compiled.group_update.critic_step.compilation.compiled and not eager.group_update.critic_step.compilation.compiled
    compiled.train_epoch()
    eager.train_epoch()
    first = [dict(run.last_row) for run in compiled.runs]
    graphs = counters["stats"]["unique_graphs"]
    for _ in range(2):
        compiled.train_epoch()
    assert counters["stats"]["unique_graphs"] == graphs, "a later epoch recompiled"
    assert compiled.group_update.critic_step.compilation.compile_error is None and compiled.optimizer.compilation.compile_error is None
    for row, reference in zip(first, (run.last_row for run in eager.runs)):
        for name, value in reference.items():
            if name.startswith(("Misc/", "Train/KL", "Loss/Loss_actor")):
                assert row[name] == value, name
            elif name.startswith("Loss/"):
                assert row[name] == pytest.approx(value, rel=1e-4), name
