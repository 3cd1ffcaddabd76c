"""sg-train with the multi-agent algorithms: config rows, one epoch each, heterogeneous agents, exact resume, CLI, recipe.

``--seed s`` runs the multi-agent family (``MultiAgentGroupTrainer``) with one seed in a single run's
layout; a checkpoint of the single-seed trainer it replaced still resumes, bit for bit
(``tests/data/multi_agent_trainer_run/checkpoint.pt``: MAPPO-Lag after epoch 1 of 2, written by that trainer).

Tiny settings (one or two simulators, small networks) on Safety2x3HalfCheetahVelocity-v0; an epoch
of 1000 steps on one simulator finishes one episode, so the episode metrics are defined.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)

from sg_torchrl.train import MultiAgentGroupTrainer, TrainConfig, main, trainer_class  # noqa: E402
from sg_torchrl.train.checkpoint import load_checkpoint  # noqa: E402
from sg_torchrl.train.command_line import parse_args  # noqa: E402
from sg_torchrl.train.config import MULTI_AGENT_ALGORITHM_NAMES  # noqa: E402
from sg_torchrl.train.multi_agent import MULTI_AGENT_ALGORITHMS, num_minibatches  # noqa: E402
from trainer_checks import assert_same_state  # noqa: E402

ENV_ID = "Safety2x3HalfCheetahVelocity-v0"
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "multi_agent.py"
#: A run directory holding a checkpoint of the single-seed multi-agent trainer this engine replaced.
OLD_RUN = Path(__file__).resolve().parent / "data" / "multi_agent_trainer_run"


def tiny_config(tmp_path, **overrides) -> TrainConfig:
    values = dict(
        algo="mappo_lag", env_id=ENV_ID, num_envs=1, steps_per_epoch=1000, total_steps=1000, update_iters=2,
        hidden_sizes=[32, 32], eval_episodes=0, wandb="disabled", progress=False, output_dir=str(tmp_path),
        run_name="run", checkpoint_every=100,
    )
    values.update(overrides)
    return TrainConfig(**values)


def flat(modules) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1).clone() for m in modules for p in m.parameters()])


class TestConfig:
    def test_table_rows_and_paper_defaults(self):
        assert set(MULTI_AGENT_ALGORITHMS) == set(MULTI_AGENT_ALGORITHM_NAMES) == {"mappo", "happo", "mappo_lag", "macpo"}
        for algo in ("mappo", "happo", "mappo_lag"):
            cfg = TrainConfig(algo=algo)
            assert cfg.env_id == ENV_ID and cfg.network_sizes == [128, 128]
            assert (cfg.steps_per_epoch, cfg.num_envs, cfg.actor_lr, cfg.critic_lr) == (10_000, 10, 5e-4, 5e-4)
            assert (cfg.update_iters, num_minibatches(cfg), cfg.clip_ratio, cfg.target_kl) == (5, 1, 0.2, 0.016)
            assert (cfg.lagrangian_init, cfg.lagrangian_lr, cfg.max_grad_norm) == (1e-5, 0.78, 10.0)
            assert cfg.normalize_obs is True  # stands in for the input LayerNorm of SafePO's networks
        macpo = TrainConfig(algo="macpo")
        assert (macpo.target_kl, macpo.cg_iters, macpo.line_search_steps, macpo.step_fraction) == (0.01, 10, 10, 0.5)
        assert macpo.update_iters == 15 and macpo.second_order and macpo.network_sizes == [128, 128]
        assert num_minibatches(TrainConfig(algo="mappo", minibatch_size=2500)) == 4
        assert parse_args(["--algo", "happo", "--normalize-obs", "false"]).normalize_obs is False

    @pytest.mark.parametrize(
        "algo, env_id",
        [("mappo_lag", "SafetyHalfCheetahVelocity-v1"), ("macpo", "SafetyPointGoal1-v0"),
         ("ppo_lag", ENV_ID), ("cpo", "Safety9|8HumanoidVelocity-v0")],
    )
    def test_mismatched_algorithm_and_env_is_a_clear_error(self, algo, env_id):
        kind = "multi-agent" if algo in MULTI_AGENT_ALGORITHM_NAMES else "single-agent"
        with pytest.raises(ValueError, match=rf"algo '{algo}' is a {kind} algorithm but env_id '{env_id}'") as error:
            TrainConfig(algo=algo, env_id=env_id)
        assert "give a" in str(error.value)

    def test_cli_reports_the_mismatch(self, capsys):
        assert main(["--algo", "mappo", "--env-id", "SafetyAntVelocity-v1"]) == 2
        err = capsys.readouterr().err
        assert "multi-agent algorithm" in err and "SafetyAntVelocity-v1" in err

    def test_dispatch(self, tmp_path):
        assert trainer_class(tiny_config(tmp_path)) is MultiAgentGroupTrainer
        with pytest.raises(ValueError, match="multi-agent algorithms"):
            MultiAgentGroupTrainer(TrainConfig(algo="ppo_lag"))
        assert trainer_class(tiny_config(tmp_path, seeds=[0, 1], run_name=None)) is MultiAgentGroupTrainer


class TestTraining:
    @pytest.mark.parametrize("algo", MULTI_AGENT_ALGORITHM_NAMES)
    def test_every_algorithm_trains_one_epoch(self, tmp_path, algo):
        # Cost limit 0 with a cost-free random policy: J_c - d = 0, the constraint is active at the boundary.
        trainer = MultiAgentGroupTrainer(tiny_config(tmp_path, algo=algo, cost_limit=0.0))
        nets = trainer.teams[0].networks
        actors, critics = flat([nets.policy]), flat([nets.reward_value, nets.cost_value])
        metrics = trainer.train_epoch()
        assert all(math.isfinite(value) for value in metrics.values()), metrics
        assert metrics["Train/TotalSteps"] == 1000 and metrics["Metrics/EpLen"] == 1000
        for name in ("Metrics/EpRet", "Metrics/EpCost", "Loss/Loss_reward_critic", "Loss/Loss_cost_critic",
                     "Train/KL", "Misc/Entropy", "Train/LagrangeMultiplier"):
            assert name in metrics, name
        for agent in range(2):  # per-agent metrics next to the team's
            assert f"Loss/Loss_reward_critic/agent{agent}" in metrics and f"Train/AgentOrder/agent{agent}" in metrics
        assert not torch.equal(critics, flat([nets.reward_value, nets.cost_value]))
        accepted = any(metrics.get(f"Misc/AcceptanceStep/agent{i}", 0) > 0 for i in range(2))
        if algo != "macpo" or accepted:  # a rejected MACPO line search leaves the actors
            assert not torch.equal(actors, flat([nets.policy]))

    def test_heterogeneous_agents_train_one_epoch(self, tmp_path):
        # HalfCheetah 6x1: six one-joint agents whose observations differ in size (padded to the largest).
        trainer = MultiAgentGroupTrainer(tiny_config(tmp_path, algo="happo", steps_per_epoch=500,
                                                     env_id="Safety6x1HalfCheetahVelocity-v0", total_steps=500))
        assert trainer.teams[0].networks.n_agents == 6 and len(set(trainer.base_env.observation_sizes)) > 1
        metrics = trainer.train_epoch()
        assert all(math.isfinite(metrics[f"Loss/Loss_actor/agent{i}"]) for i in range(6))
        assert sorted(int(metrics[f"Train/AgentOrder/agent{i}"]) for i in range(6)) == list(range(6))

    def test_observation_normalisation(self, tmp_path):
        trainer = MultiAgentGroupTrainer(tiny_config(tmp_path, algo="mappo", steps_per_epoch=100,
                                                     total_steps=100))
        trainer.train_epoch()
        observation, state = trainer.obs_norms  # one row of statistics: the one seed's
        assert observation.mean.shape == (1, 2, trainer.base_env.observation_dim) and state.mean.shape == (1, 17)
        assert observation.count.item() == state.count.item() == pytest.approx(100, abs=1e-3)
        raw = MultiAgentGroupTrainer(tiny_config(tmp_path / "raw", algo="mappo", normalize_obs=False))
        assert raw.obs_norms == [] and raw.env is raw.base_env

    def test_resume_continues_exactly(self, tmp_path):
        options = dict(algo="mappo_lag", num_envs=2, steps_per_epoch=200, total_steps=600, cost_limit=0.0)
        uninterrupted = MultiAgentGroupTrainer(tiny_config(tmp_path / "a", **options))
        uninterrupted.run()

        first_half = MultiAgentGroupTrainer(tiny_config(tmp_path / "b", **options))
        first_half.run(max_epochs=2)
        checkpoint = MultiAgentGroupTrainer.load_checkpoint(first_half.checkpoint_path.parent)
        resumed = MultiAgentGroupTrainer(tiny_config(tmp_path / "b", **options), checkpoint)
        assert resumed.epoch == 2
        resumed.run()

        team, resumed_team = uninterrupted.teams[0], resumed.teams[0]
        assert torch.equal(flat([team.networks]), flat([resumed_team.networks]))
        for a, b in zip(uninterrupted.round.multipliers, resumed.round.multipliers, strict=True):
            assert torch.equal(a.value, b.value)
        assert torch.equal(uninterrupted.obs_norms[0].mean, resumed.obs_norms[0].mean)
        rows_a = (tmp_path / "a" / "run" / "progress.csv").read_text().splitlines()
        rows_b = (tmp_path / "b" / "run" / "progress.csv").read_text().splitlines()
        assert len(rows_a) == len(rows_b) == 4  # header + 3 epochs, the resumed run appended
        columns = rows_a[0].split(",")
        keep = [i for i, name in enumerate(columns) if not name.startswith("Time/")]
        assert [[r.split(",")[i] for i in keep] for r in rows_a] == [[r.split(",")[i] for i in keep] for r in rows_b]

    def test_cli_run_writes_logs_evaluation_and_plot(self, tmp_path, capsys):
        code = main(["--algo", "macpo", "--env-id", ENV_ID, "--num-envs", "1", "--steps-per-epoch", "1000",
                     "--total-steps", "1000", "--update-iters", "1", "--hidden-sizes", "16", "--eval-episodes", "1",
                     "--wandb", "disabled", "--progress", "false", "--output-dir", str(tmp_path), "--run-name", "cli"])
        assert code == 0
        run = tmp_path / "cli"
        for name in ("progress.csv", "checkpoint.pt", "curves.png", "config.json", "summary.json", "csv"):
            assert (run / name).exists(), name
        assert not list(run.glob("seed-*"))  # the single-seed layout: no seed-XXX/ level
        header = (run / "progress.csv").read_text().splitlines()[0].split(",")
        for metric in ("Metrics/EpRet", "Metrics/EpCost", "Train/LagrangeMultiplier", "Misc/CPOCase",
                       "Misc/CPOCase/agent0", "Loss/Loss_cost_critic/agent1", "Time/FPS"):
            assert metric in header, metric
        summary = json.loads((run / "summary.json").read_text())
        assert summary["Metrics/EvalEpLen"] == 1000.0 and math.isfinite(summary["Metrics/EvalEpRet"])
        assert "seeds" not in summary and "mean" not in summary  # a run's summary, not a group's
        assert json.loads((run / "config.json").read_text())["seeds"] == []
        assert "MACPO on Safety2x3HalfCheetahVelocity-v0, seed 0: 1000 env steps" in capsys.readouterr().out

    def test_a_checkpoint_of_the_replaced_single_seed_trainer_is_converted_and_resumes(self, tmp_path):
        old = tmp_path / "old"
        shutil.copytree(OLD_RUN, old)
        saved = load_checkpoint(old)
        assert "networks" in saved and "seeds" not in saved and saved["epoch"] == 1  # the replaced trainer's layout
        options = {name: saved["config"][name] for name in (
            "algo", "env_id", "env_options", "num_envs", "steps_per_epoch", "total_steps", "update_iters",
            "hidden_sizes", "cost_limit", "eval_episodes", "seed")}
        # its round state (per-agent torch.optim.Adam state dicts, multipliers, PopArt, generator) is read into the
        # seed-batched round's stacks and written back unchanged
        loaded = MultiAgentGroupTrainer(tiny_config(tmp_path / "loaded", **options), saved)
        assert_same_state(loaded.round.seed_state_dict(0), saved["update"], "update", timings=True, nan_equal=False)
        assert main(["--resume", str(old), "--progress", "false"]) == 0
        fresh = MultiAgentGroupTrainer(tiny_config(tmp_path / "new", **options))
        fresh.run()

        def rows(run_dir):  # as numbers: epoch 1's row came from the checkpoint here ("1.0" for "1")
            with (run_dir / "progress.csv").open() as handle:
                return [{k: float(v) if v else None for k, v in row.items() if not k.startswith("Time/")}
                        for row in csv.DictReader(handle)]

        resumed, expected = rows(old), rows(fresh.cfg.run_dir)
        assert len(resumed) == len(expected) == 3  # two epochs and the evaluation
        # epoch 1 was trained by the replaced per-agent round, epoch 2 by the seed-batched round from its converted
        # state: the seed-batched round computes what the replaced one did, so the runs agree bit for bit
        assert resumed == expected
        assert load_checkpoint(old)["epoch"] == 2


@pytest.mark.timeout(120)
def test_recipe_runs_two_tiny_epochs():
    args = ["--algo", "mappo_lag", "--total-steps", "2000", "--steps-per-epoch", "1000", "--num-envs", "1",
            "--epochs-per-round", "1"]
    result = subprocess.run([sys.executable, str(EXAMPLE), *args], capture_output=True, text=True, timeout=110)
    assert result.returncode == 0, result.stderr[-2000:]
    lines = [line for line in result.stdout.splitlines() if line.startswith("epoch ")]
    assert len(lines) == 2 and "EpCost" in lines[-1] and "nan" not in lines[-1].lower()
