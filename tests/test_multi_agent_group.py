"""Multi-agent seed groups (``sg-train --algo mappo_lag --seeds 0 1``): every seed trains as its single-seed run.

What is compared, and how closely:

* **per-agent normaliser rows** (``RunningObservationNorm((agents, features), groups=S)``) against
  ungrouped normalisers fed one block each: bit for bit;
* **seed s of a group of two against the single-seed run with seed s** (``--seed s``: the same class with
  S = 1 in a single run's layout, whose runs ``tests/test_golden_equivalence.py`` holds to the
  recorded numbers; MAPPO-Lag, MACPO, HAPPO), two epochs: every entry of both epochs' batches (observations, actions, log-probs,
  rewards, costs, dones, state) bit for bit, every ``progress.csv`` column but the timings, the
  evaluation and the parameters after the run **exactly** (tolerance 0). The group stacks the seeds'
  networks and acts for every seed in one call, each seed's noise from its own generator, and updates
  the seeds' agents of a stage in one call whose every operation rounds a row as it rounds it alone
  (``addmm`` per row, per-seed reductions), so nothing is rounded differently;
* **the stacked networks**: the one-call policy against each seed's team actor (noise from the global
  RNG at the same state) bit for bit, frozen seeds idle; each team's parameters are views of the stack;
* **resume**: a group checkpointed after epoch 1 and continued equals the uninterrupted group bit for
  bit (rows, parameters, rounds' state, normalisers, RNG states);
* **divergence**: a seed made non-finite (before an epoch, or inside its update) is frozen, idles with
  zero actions and is reported (stderr, its ``summary.json``, the group's), while the other seed's
  rows equal those of a run without it (exactly);
* the command line: a group of two writes the layout and prints per-seed and mean figures, refuses a
  directory holding a run unless ``--overwrite``, and resumes.

Tiny settings: Safety2x3HalfCheetahVelocity-v0 with 100-step episodes and a 0.5 m/s speed limit (so
episodes finish and cost accrues in epoch 1), 2 simulators per seed, 200-step epochs, 16-unit networks.
"""

from __future__ import annotations

import copy
import csv
import json

import pytest
import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402

from sg_torchrl.envs.normalization import RunningObservationNorm  # noqa: E402
from sg_torchrl.modules import make_multi_agent_networks  # noqa: E402
from sg_torchrl.modules.stacked_multi_agent import StackedMultiAgentNetworks, StackedMultiAgentPolicy  # noqa: E402
from sg_torchrl.train import (  # noqa: E402
    MultiAgentGroupTrainer, OnPolicyGroupTrainer, TrainConfig, main, trainer_class,
)
from sg_torchrl.train.checkpoint import CHECKPOINT_NAME  # noqa: E402
from sg_torchrl.train.seed_runs import seed_entry  # noqa: E402
from trainer_checks import recording  # noqa: E402

ENV_ID = "Safety2x3HalfCheetahVelocity-v0"
OPTIONS = {"max_episode_steps": 100, "velocity_threshold": 0.5}


def config(tmp_path, **overrides) -> TrainConfig:
    values = dict(
        algo="mappo_lag", env_id=ENV_ID, env_options=dict(OPTIONS), num_envs=2, steps_per_epoch=200, total_steps=400,
        update_iters=2, hidden_sizes=[16, 16], cost_limit=0.0, eval_episodes=0, wandb="disabled", progress=False,
        output_dir=str(tmp_path), checkpoint_every=100,
    )
    values.update(overrides)
    return TrainConfig(**values)


def progress(run_dir) -> list[dict[str, str]]:
    with (run_dir / "progress.csv").open() as handle:
        return [{k: v for k, v in row.items() if not k.startswith("Time/")} for row in csv.DictReader(handle)]


def epochs(run_dir) -> list[int]:
    return [int(float(row["Train/Epoch"])) for row in progress(run_dir) if row["Train/Epoch"]]


def parameters(team) -> list[torch.Tensor]:
    return [p.detach().clone() for p in team.networks.parameters()]


# --------------------------------------------------------------------------- config and dispatch
def test_the_config_takes_multi_agent_groups_and_picks_their_trainer(tmp_path):
    for algo in ("mappo", "happo", "mappo_lag", "macpo"):
        cfg = TrainConfig(algo=algo, seeds=[0, 1])
        assert cfg.group and cfg.multi_agent and trainer_class(cfg) is MultiAgentGroupTrainer
    with pytest.raises(ValueError, match="multi-agent algorithms"):
        MultiAgentGroupTrainer(TrainConfig(algo="ppo_lag", seeds=[0], output_dir=str(tmp_path)))
    with pytest.raises(ValueError, match="MultiAgentGroupTrainer"):
        OnPolicyGroupTrainer(config(tmp_path, seeds=[0]))
    assert trainer_class(config(tmp_path)) is MultiAgentGroupTrainer  # one seed: the same class, a single run's layout


def test_grouped_per_agent_normaliser_rows_follow_their_blocks_bit_for_bit():
    groups, n, shape = 3, 4, (2, 5)
    grouped = RunningObservationNorm(shape, groups=groups)
    singles = [RunningObservationNorm(shape) for _ in range(groups)]
    generator = torch.Generator().manual_seed(1)
    for step in range(6):
        batch = torch.randn(groups * n, *shape, generator=generator) * (step + 1) + step
        grouped.update(batch)
        normalised = grouped._apply_transform(batch)
        for g, single in enumerate(singles):
            block = batch[g * n:(g + 1) * n]
            single.update(block)
            assert torch.equal(normalised[g * n:(g + 1) * n], single._apply_transform(block))
    for g, single in enumerate(singles):
        for name, value in single.state_dict().items():
            assert torch.equal(grouped.group_state_dict(g)[name], value), name


# --------------------------------------------------------------------------- stacked networks
@pytest.mark.parametrize("hidden, sizes, n", [((16, 16), [3, 3], 2), ((32, 32), [3, 1, 2], 1), ((128, 128), [3, 3], 10)])
def test_the_stacked_policy_is_each_seeds_team_actor_bit_for_bit(hidden, sizes, n):
    seeds = 3
    teams, states = [], []
    for seed in range(seeds):  # as the engine builds them: each team after manual_seed(seed)
        torch.manual_seed(seed)
        teams.append(make_multi_agent_networks(12, sizes, 17, hidden_sizes=hidden))
        states.append(torch.get_rng_state())
    alone = copy.deepcopy(teams)
    stacked = StackedMultiAgentNetworks(teams)
    policy = StackedMultiAgentPolicy(stacked, [torch.Generator().set_state(state) for state in states], n)
    observation = torch.randn(seeds * n, len(sizes), 12)
    for step in range(3):
        if step == 2:  # seed 1 frozen (its actions might not be finite): zeros, no noise drawn
            policy.frozen = torch.tensor([False, True, False])
        td = policy(TensorDict({"agents": {"observation": observation}}, [seeds * n]))
        for seed in range(seeds):
            block = td["agents"][seed * n:(seed + 1) * n]
            if step == 2 and seed == 1:
                assert (block["action"] == 0).all() and (block["scale"] == 1).all() and (block["action_log_prob"] == 0).all()
                continue
            torch.set_rng_state(states[seed])  # the single-seed run draws its noise from the global RNG
            single = alone[seed].actor(TensorDict({"agents": {"observation": observation[seed * n:(seed + 1) * n]}}, [n]))
            states[seed] = torch.get_rng_state()
            for key in ("loc", "scale", "action", "action_log_prob"):
                assert torch.equal(block[key], single["agents", key]), (seed, step, key)
        observation = observation + 0.1


def test_each_team_is_a_view_of_the_stack():
    torch.manual_seed(0)
    teams = [make_multi_agent_networks(12, [3, 2], 17, hidden_sizes=(16, 16)) for _ in range(2)]
    copies = copy.deepcopy(teams)
    stacked = StackedMultiAgentNetworks(teams)
    for team, before in zip(teams, copies):
        assert all(torch.equal(a, b) for a, b in zip(team.state_dict().values(), before.state_dict().values()))
    optimizer = torch.optim.Adam(teams[1].agent_actor(0).parameters(), lr=0.1)
    teams[1].agent_actor(0).module[0].module.net[0].weight.sum().backward()  # the first layer of seed 1, agent 0
    optimizer.step()
    moved = stacked.weights["policy"][0]
    assert not torch.equal(moved[1, 0], copies[1].policy.mlp.agent_networks[0][0].weight)
    assert torch.equal(moved[0], torch.stack([net[0].weight for net in copies[0].policy.mlp.agent_networks]))
    teams[0].load_state_dict(copies[1].state_dict())  # a checkpoint loads into the stack's rows
    assert torch.equal(stacked.log_std[0, 1, :2], copies[1].policy.heads[1].log_std)
    with torch.no_grad():
        teams[1].cost_value.mlp.agent_networks[1][2].bias[0] = float("nan")
    assert stacked.finite_seeds().tolist() == [True, False]


# --------------------------------------------------------------------------- equivalence
@pytest.mark.parametrize("algo", ["mappo_lag", "macpo", "happo"])
def test_each_seed_of_a_group_is_its_single_seed_run_bit_for_bit(tmp_path, algo):
    seeds = [0, 1]
    group = MultiAgentGroupTrainer(config(tmp_path / "group", algo=algo, seeds=seeds, eval_episodes=1))
    group_batches = recording(group)
    metrics = group.run()
    for index, seed in enumerate(seeds):
        single = MultiAgentGroupTrainer(config(tmp_path / f"single{seed}", algo=algo, seed=seed, eval_episodes=1))
        single_batches = recording(single)
        single_metrics = single.run()
        block = slice(2 * index, 2 * index + 2)
        for epoch, (mine, alone) in enumerate(zip(group_batches, single_batches, strict=True)):
            keys = list(alone.keys(True, True))
            assert set(keys) == set(group_batches[epoch].keys(True, True))
            for key in keys:
                assert torch.equal(mine[key][block], alone[key]), (seed, epoch, key)
        rows, expected = progress(group.cfg.seed_dir(seed)), progress(single.cfg.run_dir)
        assert len(rows) == len(expected) == 3 and rows == expected  # two epochs and the evaluation, exactly
        for name in ("Metrics/EvalEpRet", "Metrics/EvalEpCost", "Final/EpRetLast10"):
            assert metrics[f"seed-{seed:03d}/{name}"] == single_metrics[name], name
        for mine, alone in zip(parameters(group.teams[index]), parameters(single.teams[0]), strict=True):
            assert torch.equal(mine, alone)
        for norm, alone in zip(group.obs_norms, single.obs_norms, strict=True):
            assert torch.equal(norm.group_state_dict(index)["mean"], alone.group_state_dict(0)["mean"])
        first = expected[0]
        assert float(first["Metrics/EpCost"]) > 0  # cost to follow in epoch 1
        if algo == "mappo_lag":
            assert float(first["Train/LagrangeMultiplier"]) > 1e-5  # the multipliers moved from their init


# --------------------------------------------------------------------------- resume
@pytest.mark.parametrize("algo", ["mappo_lag", "macpo"])
def test_resume_continues_the_group_bit_for_bit(tmp_path, algo):
    uninterrupted = MultiAgentGroupTrainer(config(tmp_path / "a", algo=algo, seeds=[0, 1], total_steps=600))
    uninterrupted.run()

    first = MultiAgentGroupTrainer(config(tmp_path / "b", algo=algo, seeds=[0, 1], total_steps=600))
    first.run(max_epochs=1)
    checkpoint = MultiAgentGroupTrainer.load_checkpoint(first.cfg.run_dir)
    resumed = MultiAgentGroupTrainer(config(tmp_path / "b", algo=algo, seeds=[0, 1], total_steps=600), checkpoint)
    assert resumed.epoch == 1
    resumed.run()

    for index, seed in enumerate([0, 1]):
        for mine, theirs in zip(parameters(resumed.teams[index]), parameters(uninterrupted.teams[index])):
            assert torch.equal(mine, theirs)
        assert torch.equal(resumed.policy.generators[index].get_state(), uninterrupted.policy.generators[index].get_state())
        update, reference = resumed.round.seed_state_dict(index), uninterrupted.round.seed_state_dict(index)
        assert torch.equal(update["generator"], reference["generator"])
        for mine, theirs in zip(update["multipliers"].values(), reference["multipliers"].values(), strict=True):
            assert torch.equal(mine, theirs)
        for mine, theirs in zip(update["optimizers"], reference["optimizers"], strict=True):
            assert mine["state"].keys() == theirs["state"].keys()
            for key in mine["state"]:
                assert all(torch.equal(mine["state"][key][name], theirs["state"][key][name]) for name in mine["state"][key])
        rows = progress(resumed.cfg.seed_dir(seed))
        assert len(rows) == 3 and rows == progress(uninterrupted.cfg.seed_dir(seed))
    for mine, theirs in zip(resumed.obs_norms, uninterrupted.obs_norms):
        assert torch.equal(mine.mean, theirs.mean) and torch.equal(mine.var, theirs.var)
    entry = seed_entry(checkpoint, 1)
    assert entry["config"]["seed"] == 1 and {"networks", "update", "obs_norms", "torch_rng"} <= set(entry)


# --------------------------------------------------------------------------- divergence
def test_a_diverged_seed_is_frozen_and_reported_while_the_other_trains_on(tmp_path, capsys):
    cfg = config(tmp_path / "nan", seeds=[0, 1], total_steps=600)
    broken = MultiAgentGroupTrainer(cfg)
    batches = recording(broken)
    broken.run(max_epochs=1)
    with torch.no_grad():
        next(broken.teams[1].networks.policy.parameters()).view(-1)[0] = float("nan")  # between epochs 1 and 2
    metrics = broken.run()
    assert "seed 1 diverged in epoch 2" in capsys.readouterr().err
    idle = batches[1]["agents", "action"][2:4]
    assert torch.equal(idle, torch.zeros_like(idle)) and torch.isfinite(batches[1]["agents", "loc"]).all()
    assert epochs(cfg.seed_dir(1)) == [1]
    summary = json.loads((cfg.seed_dir(1) / "summary.json").read_text())
    assert summary["Diverged"] is True and summary["DivergedEpoch"] == 2
    assert json.loads((cfg.run_dir / "summary.json").read_text())["diverged"] == [1]
    assert metrics["seed-001/Diverged"] is True and metrics["Train/Epoch"] == 3

    clean = MultiAgentGroupTrainer(config(tmp_path / "clean", seeds=[0], total_steps=600))
    clean.run()
    assert progress(cfg.seed_dir(0)) == progress(clean.cfg.seed_dir(0))  # the other seed, exactly


def test_a_seed_whose_update_turns_non_finite_is_put_back_and_frozen(tmp_path, capsys):
    group = MultiAgentGroupTrainer(config(tmp_path, seeds=[0, 1], total_steps=600))
    group.run(max_epochs=1)
    team = group.teams[0]
    before = parameters(team)
    step_seeds = group.round.step_seeds

    def round_then_break(batches, costs):  # seed 0's update turns non-finite in the round of both seeds
        rows = step_seeds(batches, costs)
        if batches[0] is not None:
            with torch.no_grad():
                next(team.networks.reward_value.parameters()).view(-1)[0] = float("inf")
        return rows

    group.round.step_seeds = round_then_break
    group.run()
    assert "seed 0 diverged in epoch 2 (its update turned non-finite" in capsys.readouterr().err
    assert all(torch.equal(a, b) for a, b in zip(parameters(team), before))  # put back to before epoch 2
    assert epochs(group.cfg.seed_dir(0)) == [1, 2] and epochs(group.cfg.seed_dir(1)) == [1, 2, 3]
    assert group.runs[0].diverged["epoch"] == 2 and group.runs[1].alive


# --------------------------------------------------------------------------- command line
TINY = ["--algo", "mappo_lag", "--env-id", ENV_ID, "--env-options", "max_episode_steps=100", "--num-envs", "2",
        "--steps-per-epoch", "200", "--total-steps", "400", "--update-iters", "1", "--hidden-sizes", "16",
        "--eval-episodes", "1", "--wandb", "disabled", "--progress", "false"]


def test_command_line_multi_agent_group_end_to_end(tmp_path, capsys):
    assert main(["--seeds", "0", "1", "--output-dir", str(tmp_path), *TINY]) == 0
    group_dir = tmp_path / ENV_ID / "mappo_lag" / "seeds-0-1"
    for name in (CHECKPOINT_NAME, "config.json", "summary.json", "curves.png"):
        assert (group_dir / name).exists(), name
    for seed in (0, 1):
        seed_dir = group_dir / f"seed-{seed:03d}"
        for name in ("progress.csv", "config.json", "summary.json", "curves.png", "csv"):
            assert (seed_dir / name).exists(), (seed, name)
        assert "Metrics/EvalEpRet" in json.loads((seed_dir / "summary.json").read_text())
        assert json.loads((seed_dir / "config.json").read_text())["seed"] == seed
        assert "Loss/Loss_actor/agent1" in (seed_dir / "progress.csv").read_text().splitlines()[0]
    out = capsys.readouterr().out
    assert "MAPPO-Lag on Safety2x3HalfCheetahVelocity-v0, seeds 0 1" in out
    assert "seed 0: training EpRet" in out and "seed 1: training EpRet" in out and "mean of the seeds" in out

    assert main(["--seeds", "0", "1", "--output-dir", str(tmp_path), *TINY]) == 2  # never over a group unasked
    assert "already holds a run" in capsys.readouterr().err
    assert main(["--resume", str(group_dir), "--total-steps", "600"]) == 0
    assert epochs(group_dir / "seed-001") == [1, 2, 3]
    assert main(["--seeds", "0", "1", "--overwrite", "--output-dir", str(tmp_path), *TINY]) == 0
    assert epochs(group_dir / "seed-001") == [1, 2]
