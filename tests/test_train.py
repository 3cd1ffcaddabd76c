"""sg-train: config validation, CLI overrides, a smoke run's artefacts, exact resume, evaluation."""

from __future__ import annotations

import csv
import json

import pytest
import torch

torch.set_num_threads(1)

import sg_torchrl  # noqa: E402
from sg_torchrl.train import ALGORITHMS, OnPolicyGroupTrainer, TrainConfig, main  # noqa: E402
from sg_torchrl.train.command_line import parse_args  # noqa: E402
from sg_torchrl.train.config import ALGORITHM_NAMES, SECOND_ORDER  # noqa: E402
from trainer_checks import flat_parameters, tiny_config  # noqa: E402


class TestConfig:
    def test_defaults_are_the_papers(self):
        cfg = TrainConfig()
        assert (cfg.steps_per_epoch, cfg.update_iters, cfg.minibatch_size) == (20_000, 40, 64)
        assert (cfg.gamma, cfg.gae_lambda, cfg.target_kl, cfg.clip_ratio) == (0.99, 0.95, 0.02, 0.2)
        assert (cfg.actor_lr, cfg.critic_lr, cfg.lagrangian_init, cfg.lagrangian_lr) == (3e-4, 3e-4, 1e-3, 0.035)
        assert cfg.cost_limit == 25.0 and cfg.network_sizes == [64, 64]

    def test_every_algorithm_is_in_the_table(self):
        # the paper's twelve and the one added beyond it (README, "Add an algorithm")
        assert set(ALGORITHMS) == set(ALGORITHM_NAMES) and len(ALGORITHM_NAMES) == 13

    @pytest.mark.parametrize("algo", ["cpo", "trpo_lag", "npg"])
    def test_second_order_defaults_are_the_papers(self, algo):
        cfg = TrainConfig(algo=algo)
        assert (cfg.target_kl, cfg.critic_lr, cfg.update_iters, cfg.minibatch_size) == (0.01, 1e-3, 10, 128)
        assert (cfg.cg_iters, cfg.cg_damping, cfg.line_search_steps, cfg.step_fraction) == (15, 0.1, 15, 0.8)

    def test_per_algorithm_defaults_and_explicit_values(self):
        assert TrainConfig(algo="pcpo").line_search_steps == 200
        assert TrainConfig(algo="focops").multiplier_upper_bound == 2.0
        assert TrainConfig(algo="cup").multiplier_upper_bound == 2.0
        assert TrainConfig(algo="ppo_lag").multiplier_upper_bound is None
        assert TrainConfig(algo="cpo", target_kl=0.05).target_kl == 0.05  # explicit values win
        assert parse_args(["--algo", "trpo"]).target_kl == 0.01

    @pytest.mark.parametrize(
        "env_id, sizes",
        [("SafetyPointGoal1-v0", [64, 64]), ("SafetyAntVelocity-v1", [64, 64]), ("SafetyAntGoal1-v0", [256, 256]),
         ("SafetyDoggoButton2-v0", [256, 256])],
    )
    def test_network_sizes_follow_the_paper_per_robot(self, env_id, sizes):
        # Appendix: [256, 256] for the Ant and Doggo navigation robots, [64, 64] for the rest.
        assert TrainConfig(env_id=env_id).network_sizes == sizes
        assert TrainConfig(env_id=env_id, hidden_sizes=[32]).network_sizes == [32]

    @pytest.mark.parametrize(
        "field, value, message",
        [
            ("num_envs", 0, "num_envs"),
            ("steps_per_epoch", 1001, "multiple of num_envs"),
            ("gamma", 1.5, "gamma"),
            ("actor_lr", -1.0, "actor_lr"),
            ("cost_limit", -3.0, "cost_limit"),
            ("total_steps", 10, "less than one epoch"),
            ("algo", "sac2", "unknown algo"),
            ("step_fraction", 1.0, "step_fraction"),
            ("line_search_steps", 0, "line_search_steps"),
        ],
    )
    def test_bad_values_name_the_field(self, field, value, message):
        with pytest.raises(ValueError, match=message):
            TrainConfig(**{field: value})

    def test_command_line_overrides_preset(self):
        cfg = parse_args(["--preset", "smoke", "--algo", "cppo_pid", "--seed", "7", "--hidden-sizes", "32", "16",
                          "--normalize-obs", "false", "--cost-limit", "10"])
        assert cfg.algo == "cppo_pid" and cfg.seed == 7 and cfg.hidden_sizes == [32, 16]
        assert cfg.normalize_obs is False and cfg.cost_limit == 10.0
        assert cfg.total_steps == 4_000  # from the preset

    def test_make_run_preset_is_a_seed_group(self):
        # `make run`: a group of several seeds of a first-order algorithm in one process,
        # whole epochs, a few hundred thousand steps per seed, every seed's run in runs/make-run/seed-XXX.
        cfg = parse_args(["--preset", "make-run"])  # a TrainConfig: validated when built
        assert cfg.group and len(cfg.seeds) >= 3 and cfg.seed == cfg.seeds[0]
        assert cfg.algo in ALGORITHM_NAMES and not cfg.second_order and cfg.env_id in sg_torchrl.list_envs()
        assert cfg.total_steps % cfg.steps_per_epoch == 0 and cfg.total_steps <= 500_000
        assert cfg.eval_episodes > 0 and cfg.cost_limit == 25.0
        assert str(cfg.run_dir) == "runs/make-run" and cfg.seed_dir(cfg.seeds[1]).name == f"seed-{cfg.seeds[1]:03d}"
        assert cfg.for_seed(cfg.seeds[1]).run_dir == cfg.seed_dir(cfg.seeds[1])  # each seed's own config validates

    def test_cli_reports_bad_value(self, capsys):
        assert main(["--num-envs", "3", "--steps-per-epoch", "1000"]) == 2
        assert "multiple of num_envs" in capsys.readouterr().err

    def test_env_options_from_the_command_line(self):
        cfg = parse_args(["--preset", "smoke", "--env-options", "velocity_threshold=0.5", "cost_mode=raw",
                          "max_episode_steps=200"])
        assert cfg.env_options == {"velocity_threshold": 0.5, "cost_mode": "raw", "max_episode_steps": 200}

    @pytest.mark.parametrize(
        "options, message",
        [({"lidar": "natural"}, r"HalfCheetahVelocity-v1: unknown option\(s\) 'lidar'"), ({"seed": 3}, "use --seed")],
    )
    def test_bad_env_options_are_clear_errors(self, options, message):
        with pytest.raises(ValueError, match=message):
            TrainConfig(env_options=options)

    def test_cli_rejects_an_option_without_a_value(self, capsys):
        with pytest.raises(SystemExit):
            parse_args(["--env-options", "velocity_threshold"])
        assert "not KEY=VALUE" in capsys.readouterr().err

    def test_env_options_reach_the_training_and_evaluation_envs(self, tmp_path):
        # A threshold of -1 m/s makes most steps cost 1 (84 of 100 here; the default, 3.2 m/s, almost none).
        options = {"velocity_threshold": -1.0, "max_episode_steps": 100}
        trainer = OnPolicyGroupTrainer(tiny_config(tmp_path, env_options=options, eval_episodes=2))
        assert trainer.base_env.velocity_threshold == -1.0 and trainer.base_env.max_episode_steps == 100
        row = trainer.train_epoch()
        assert row["Metrics/EpLen"] == 100.0 and row["Metrics/EpCost"] > 70
        evaluation = trainer._evaluate_seed(0)
        assert evaluation["Metrics/EvalEpLen"] == 100.0 and evaluation["Metrics/EvalEpCost"] > 70

    def test_unknown_env_id_is_a_clear_error(self, tmp_path):
        with pytest.raises(KeyError, match="Did you mean"):
            OnPolicyGroupTrainer(tiny_config(tmp_path, env_id="SafetyHalfCheetahVelocity-v3"))


class TestTraining:
    def test_smoke_run_writes_logs_checkpoint_and_plot(self, tmp_path, capsys):
        code = main(["--preset", "smoke", "--output-dir", str(tmp_path), "--run-name", "smoke",
                     "--algo", "cppo_pid"])
        assert code == 0
        run = tmp_path / "smoke"
        for name in ("progress.csv", "checkpoint.pt", "curves.png", "config.json", "summary.json"):
            assert (run / name).exists(), name
        header = (run / "progress.csv").read_text().splitlines()[0].split(",")
        for metric in ("Metrics/EpRet", "Metrics/EpCost", "Metrics/EpLen", "Train/LagrangeMultiplier", "Train/KL",
                       "Train/StopIter", "Loss/Loss_actor", "Loss/Loss_cost_critic", "Time/FPS"):
            assert metric in header, metric
        summary = json.loads((run / "summary.json").read_text())
        assert summary["Metrics/EvalEpLen"] == 1000.0
        assert "EpCost" in capsys.readouterr().out

    def test_update_changes_parameters_and_multiplier_follows_cost(self, tmp_path):
        trainer = OnPolicyGroupTrainer(tiny_config(tmp_path, cost_limit=0.0))
        before = flat_parameters(trainer).clone()
        metrics = trainer.train_epoch()
        assert not torch.equal(before, flat_parameters(trainer))
        assert 1 <= metrics["Train/StopIter"] <= 2
        assert metrics["Train/TotalSteps"] == 200

    @pytest.mark.parametrize("algo", ALGORITHM_NAMES)
    def test_every_algorithm_trains_one_epoch(self, tmp_path, algo):
        # Cost limit 0: the constraint is violated, so Lagrangian multipliers grow and CPO / PCPO
        # take their constraint-handling branches.
        # 1000 steps per simulator: every HalfCheetah episode finishes within the epoch.
        trainer = OnPolicyGroupTrainer(tiny_config(tmp_path, algo=algo, cost_limit=0.0, steps_per_epoch=2000,
                                                   total_steps=2000))
        actor, critics = trainer.model.flat_actor.clone(), trainer.model.flat_critics.clone()
        metrics = trainer.train_epoch()
        assert not torch.equal(critics, trainer.model.flat_critics)
        moved = not torch.equal(actor, trainer.model.flat_actor)
        assert moved or metrics.get("Misc/AcceptanceStep") == 0  # a rejected line search leaves the actor
        for name in ("Metrics/EpRet", "Train/KL", "Loss/Loss_actor", "Loss/Loss_reward_critic",
                     "Loss/Loss_cost_critic", "Train/LagrangeMultiplier"):
            assert name in metrics and metrics[name] == metrics[name], name  # present and not NaN
        if algo in SECOND_ORDER:
            for name in ("Misc/xHx", "Misc/H_inv_g", "Misc/AcceptanceStep", "Misc/FinalStepNorm"):
                assert torch.isfinite(torch.tensor(metrics[name])), name
        if algo == "cpo":
            assert metrics["Misc/CPOCase"] in (0.0, 1.0, 2.0, 3.0, 4.0)
        lagrangian = algo in ("ppo_lag", "cppo_pid", "focops", "cup", "trpo_lag", "rcpo", "ppo_lag_pessimistic")
        assert (metrics["Train/LagrangeMultiplier"] > 0) == lagrangian

    @pytest.mark.parametrize("algo", ["ppo_lag", "cup", "cpo"])
    def test_resume_continues_exactly(self, tmp_path, algo):
        uninterrupted = OnPolicyGroupTrainer(tiny_config(tmp_path / "a", algo=algo))
        uninterrupted.run()

        first_half = OnPolicyGroupTrainer(tiny_config(tmp_path / "b", algo=algo))
        first_half.run(max_epochs=2)
        checkpoint = OnPolicyGroupTrainer.load_checkpoint(first_half.checkpoint_path.parent)
        resumed = OnPolicyGroupTrainer(tiny_config(tmp_path / "b", algo=algo), checkpoint)
        assert resumed.epoch == 2
        resumed.run()

        assert torch.equal(flat_parameters(uninterrupted), flat_parameters(resumed))
        assert torch.equal(uninterrupted.multipliers[0].value, resumed.multipliers[0].value)
        assert torch.equal(uninterrupted.obs_norm.mean, resumed.obs_norm.mean)
        rows_a = (tmp_path / "a" / "run" / "progress.csv").read_text().splitlines()
        rows_b = (tmp_path / "b" / "run" / "progress.csv").read_text().splitlines()
        assert len(rows_a) == len(rows_b) == 4  # header + 3 epochs, the resumed run appended
        assert [r.split(",")[:3] for r in rows_a] == [r.split(",")[:3] for r in rows_b]

    def test_resume_after_a_crash_past_the_checkpoint_logs_each_epoch_once(self, tmp_path):
        # Checkpoint after epoch 1, the run logs epochs 2 and 3 and dies: resuming from epoch 1 logs
        # epochs 2 and 3 again, and progress.csv must not hold them twice.
        crashed = OnPolicyGroupTrainer(tiny_config(tmp_path, total_steps=800, checkpoint_every=1))
        crashed.run(max_epochs=1)
        checkpoint = OnPolicyGroupTrainer.load_checkpoint(crashed.checkpoint_path.parent)
        crashed.cfg.checkpoint_every = 100
        crashed.run(max_epochs=2)
        progress = tmp_path / "run" / "progress.csv"
        assert len(progress.read_text().splitlines()) == 4  # header + epochs 1-3
        resumed = OnPolicyGroupTrainer(tiny_config(tmp_path, total_steps=800, checkpoint_every=1), checkpoint)
        resumed.run()
        with progress.open() as handle:
            epochs = [int(float(row["Train/Epoch"])) for row in csv.DictReader(handle)]
        assert epochs == [1, 2, 3, 4]

    def test_resuming_a_finished_run_keeps_one_final_row(self, tmp_path):
        finished = OnPolicyGroupTrainer(tiny_config(tmp_path, eval_episodes=1))
        finished.run()
        progress = tmp_path / "run" / "progress.csv"
        rows = progress.read_text().splitlines()
        checkpoint = OnPolicyGroupTrainer.load_checkpoint(finished.checkpoint_path.parent)
        resumed = OnPolicyGroupTrainer(tiny_config(tmp_path, eval_episodes=1), checkpoint)
        resumed.run()
        assert progress.read_text().splitlines()[:-1] == rows[:-1]  # the epochs, once
        assert len(progress.read_text().splitlines()) == len(rows)  # and one final row

    def test_missing_checkpoint_is_a_clear_error(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="no checkpoint"):
            OnPolicyGroupTrainer.load_checkpoint(tmp_path)


class TestLogging:
    def test_wandb_offline_needs_no_account(self, tmp_path, monkeypatch):
        monkeypatch.delenv("WANDB_API_KEY", raising=False)
        monkeypatch.setenv("WANDB_MODE", "dryrun")  # what torchrl's offline=True would set; must not break us
        assert main(["--preset", "smoke", "--wandb", "offline", "--output-dir", str(tmp_path), "--run-name", "w",
                     "--eval-episodes", "0"]) == 0
        runs = list((tmp_path / "w" / "wandb").glob("offline-run-*"))
        assert len(runs) == 1 and any(runs[0].glob("*.wandb"))
