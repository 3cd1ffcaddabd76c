"""Seed groups (``sg-train --seeds``): every seed of a group trains as that seed alone would.

What is compared, and how closely:

* **env blocks** (``sg_torchrl.make(seed=[...])``) against separate envs: bit for bit (each simulator
  draws from its own generator, seeded from ``(seed, i)`` whatever the batch);
* **per-seed normaliser rows** against an ungrouped normaliser fed one block: bit for bit;
* **initial networks** against ``make_actor_critics`` after ``seed_torch(seed)`` (what a user's single-seed
  code builds): bit for bit;
* **seed s of an S = 3 group against the group of s alone** (PPO-Lag, CUP, FOCOPS, and the second-order
  CPO, TRPO-Lag, PCPO): the first epoch's trajectories (observations, actions, log-probs, rewards,
  costs, dones) bit for bit, because every random number a seed uses comes from its own generators and
  simulators and the stacked actor computes each seed's actions as for S = 1; the first epoch's metrics
  (losses, KL, stop pass, multiplier, EpRet / EpCost, advantages; second order also the trust-region
  step's ``Misc/...``, its accepted trial and CPO case) to rtol 1e-4 (atol 1e-6), and the parameters
  after it to atol 1e-5: batched matmuls of the critics' one-wide last layer round differently for
  S = 1 and S = 3 (about 1e-7), which Adam's normalisation lifts to about 1e-6 on near-zero gradient
  entries. Conjugate gradient amplifies such differences, but measured on these configs the
  second-order metrics agree to 5e-7 relative (``Loss/Loss_actor``, a mean of ratio x normalised
  advantage near 1e-8, to 4e-8 absolute) and the parameters to 5e-8, so the one tolerance holds. Later
  epochs are not compared: a 1e-7 change of an action is amplified by contact dynamics like any other;
* **KL early stop**: a seed that stopped keeps its parameters, Adam moments, step counts and
  minibatch generator bit for bit while the others go on;
* **divergence**: a seed made non-finite (before an epoch, or inside its update) is frozen and
  reported, and the other seeds' logs are those of a run without it (rtol 1e-6);
* **resume**: a group checkpointed after epoch 1 and continued equals the uninterrupted group bit for
  bit (progress rows and parameters), first and second order;
* the command line: a group of two writes every per-seed file (PPO-Lag, CPO); bad ``--seeds`` exit 2.

The second-order group update against the single-seed trust-region step, frozen seeds and
divergence inside the trust-region step: ``tests/test_seed_group_second_order.py``.
"""

from __future__ import annotations

import csv
import json

import pytest
import torch

torch.set_num_threads(1)

import sg_torchrl  # noqa: E402
from sg_torchrl.envs.normalization import RunningObservationNorm  # noqa: E402
from sg_torchrl.objectives import LagrangeMultiplier, PPOLagLoss  # noqa: E402
from sg_torchrl import seeding  # noqa: E402
from sg_torchrl.train import OnPolicyGroupTrainer, TrainConfig, main  # noqa: E402
from sg_torchrl.train.checkpoint import CHECKPOINT_NAME  # noqa: E402
from sg_torchrl.train.config import ALGORITHM_NAMES  # noqa: E402
from sg_torchrl.train.fused import FusedFirstOrderStep, SeedShuffler  # noqa: E402
from sg_torchrl.train.group_updates import FirstOrderGroupUpdate, GroupParts  # noqa: E402
from sg_torchrl.modules import StackedActorCritic, make_actor_critics  # noqa: E402
from sg_torchrl.train.seed_group import seed_entry  # noqa: E402
from trainer_checks import recording, tiny_config  # noqa: E402

POINT, CHEETAH = "SafetyPointGoal1-v0", "SafetyHalfCheetahVelocity-v1"
RTOL, ATOL = 1e-4, 1e-6


def group_config(tmp_path, seeds, **overrides) -> TrainConfig:
    """PPO-Lag on HalfCheetah with 100-step episodes and a 0.5 m/s speed limit (so episodes finish and
    costs accrue in epoch 1, and the multipliers move)."""
    values = dict(
        env_id=CHEETAH, env_options={"max_episode_steps": 100, "velocity_threshold": 0.5}, num_envs=2,
        steps_per_epoch=400, total_steps=400, update_iters=3, minibatch_size=64, cost_limit=0.0, eval_episodes=0,
        wandb="disabled", progress=False, output_dir=str(tmp_path), seeds=list(seeds), checkpoint_every=100,
    )
    values.update(overrides)
    return TrainConfig(**values)


def progress(run_dir) -> list[dict[str, str]]:
    with (run_dir / "progress.csv").open() as handle:
        return list(csv.DictReader(handle))


def epochs(run_dir) -> list[int]:
    """The epochs logged in ``progress.csv`` (the evaluation's row has none)."""
    return [int(float(row["Train/Epoch"])) for row in progress(run_dir) if row["Train/Epoch"]]


def without_times(rows):
    return [{k: v for k, v in row.items() if not k.startswith("Time/")} for row in rows]


# --------------------------------------------------------------------------- simulators and normaliser
def test_a_list_of_seeds_seeds_equal_blocks_as_separate_envs():
    seeds, n = [3, 0, 7], 2
    group = sg_torchrl.make(POINT, num_envs=len(seeds) * n, seed=seeds)
    singles = [sg_torchrl.make(POINT, num_envs=n, seed=seed) for seed in seeds]
    td, tds = group.reset(), [env.reset() for env in singles]
    generator = torch.Generator().manual_seed(0)
    for _ in range(30):
        td["action"] = torch.rand(len(seeds) * n, 2, generator=generator) * 2 - 1
        for block, (env, single) in enumerate(zip(singles, tds)):
            single["action"] = td["action"][block * n:(block + 1) * n]
        out, td = group.step_and_maybe_reset(td)
        for block, env in enumerate(singles):
            expected, tds[block] = env.step_and_maybe_reset(tds[block])
            for key in ("observation", "reward", "cost", "done"):
                assert torch.equal(out["next", key][block * n:(block + 1) * n], expected["next", key]), key


@pytest.mark.parametrize("seed, message", [([0, 1], "multiple of its length"), ([], "multiple of its length"),
                                           ([0, -1, 2], "seed must be >= 0"), ([0, 1.5, 2], "seed must be an integer"),
                                           ([[0], 1, 2], "seed must be an integer")])
def test_bad_seed_lists_are_refused(seed, message):
    with pytest.raises(ValueError, match=message):
        sg_torchrl.make(POINT, num_envs=3, seed=seed)


def test_grouped_normaliser_rows_follow_their_blocks_bit_for_bit():
    groups, n, dim = 3, 4, 5
    grouped = RunningObservationNorm((dim,), groups=groups)
    singles = [RunningObservationNorm((dim,)) for _ in range(groups)]
    generator = torch.Generator().manual_seed(1)
    for step in range(6):
        batch = torch.randn(groups * n, dim, generator=generator) * (step + 1) + step
        grouped.update(batch)
        normalised = grouped._apply_transform(batch)
        for g, single in enumerate(singles):
            single.update(batch[g * n:(g + 1) * n])
            assert torch.equal(normalised[g * n:(g + 1) * n], single._apply_transform(batch[g * n:(g + 1) * n]))
    for g, single in enumerate(singles):
        for name, value in single.state_dict().items():
            assert torch.equal(grouped.group_state_dict(g)[name], value), name
        assert torch.equal(grouped.group_copy(g).mean, single.mean)


# --------------------------------------------------------------------------- equivalence
def test_each_seed_starts_from_its_single_seed_networks(tmp_path):
    group = OnPolicyGroupTrainer(group_config(tmp_path / "g", [4, 9], env_options={}))
    env = group.base_env
    for index, seed in enumerate([4, 9]):
        seeding.seed_torch(seed)
        single = make_actor_critics(env.observation_spec, env.action_spec, group.cfg.network_sizes)
        exported = group.model.export_seed(index, env.action_spec)
        ours = torch.cat([p.detach().reshape(-1) for m in exported for p in m.parameters()])
        assert torch.equal(ours, torch.cat([p.detach().reshape(-1) for m in single for p in m.parameters()]))


@pytest.mark.parametrize("algo", ["ppo_lag", "cup", "focops", "cpo", "trpo_lag", "pcpo"])
def test_a_seed_of_three_follows_its_group_of_one(tmp_path, algo):
    seeds, costs = [0, 1, 2], []
    three = OnPolicyGroupTrainer(group_config(tmp_path / "three", seeds, algo=algo))
    batches_three = recording(three)
    three.run()
    for index, seed in enumerate(seeds):
        one = OnPolicyGroupTrainer(group_config(tmp_path / f"one{seed}", [seed], algo=algo))
        batches_one = recording(one)
        one.run()
        block = slice(2 * index, 2 * index + 2)
        for key in ("observation", "action", "action_log_prob", "loc", ("next", "observation"), ("next", "reward"),
                    ("next", "cost"), ("next", "done")):
            assert torch.equal(batches_three[0][key][block], batches_one[0][key]), (seed, key)
        row_three = without_times(progress(three.cfg.seed_dir(seed)))[0]
        row_one = without_times(progress(one.cfg.seed_dir(seed)))[0]
        assert row_three.keys() == row_one.keys()
        for name in row_one:
            assert float(row_three[name]) == pytest.approx(float(row_one[name]), rel=RTOL, abs=ATOL, nan_ok=True), name
        costs.append((float(row_one["Metrics/EpCost"]), float(row_one["Train/LagrangeMultiplier"])))
        for mine, alone in zip(three.model.flat_groups, one.model.flat_groups):
            torch.testing.assert_close(mine[index], alone[0], rtol=0, atol=1e-5)
    assert all(cost > 0 for cost, _ in costs)  # costs to follow (CPO / PCPO: in the step, no multiplier)
    assert all(lam > 1e-3 if algo not in ("cpo", "pcpo") else lam == 0.0 for _, lam in costs)


def test_per_seed_files_have_the_single_seed_runs_columns(tmp_path):
    for algo in ("ppo_lag", "cup", "cpo"):
        OnPolicyGroupTrainer(tiny_config(tmp_path / algo, algo=algo, total_steps=200)).run()
        group = OnPolicyGroupTrainer(group_config(tmp_path / f"g-{algo}", [5], algo=algo))
        group.run()
        single_header = (tmp_path / algo / "run" / "progress.csv").read_text().splitlines()[0]
        assert (group.cfg.seed_dir(5) / "progress.csv").read_text().splitlines()[0] == single_header
        saved = json.loads((group.cfg.seed_dir(5) / "config.json").read_text())
        assert saved["seed"] == 5 and saved["seeds"] == [] and saved["run_name"] == "seed-005"


# --------------------------------------------------------------------------- KL stop and divergence
def synthetic_update(passes: int, target_kl: float, nan_seed: int | None = None):
    """A two-seed PPO-Lag group update on synthetic data; seed 1's advantages are zero, so its actor never moves."""
    seeds, obs_dim, size = (3, 11), 6, 256
    spec = sg_torchrl.make("SafetyHalfCheetahVelocity-v1").action_spec
    nets = []
    for seed in seeds:
        torch.manual_seed(seed)
        nets.append(make_actor_critics(obs_dim, spec, [16, 16]))
    model = StackedActorCritic.from_single(nets)
    optimizer = FusedFirstOrderStep.make_optimizer(model, 3e-4, 3e-4, max_grad_norm=40.0)
    parts = GroupParts(model, optimizer, SeedShuffler(seeds), passes=passes, minibatch_size=32, target_kl=target_kl)
    loss = PPOLagLoss(*nets[0], LagrangeMultiplier(cost_limit=0.0), critic_l2_coeff=1e-3, functional=False)
    update = FirstOrderGroupUpdate(parts, loss.seed_batched_objective())
    generator = torch.Generator().manual_seed(0)
    obs = torch.randn(2, size, obs_dim, generator=generator)
    action, log_prob, loc, scale = model.sample(obs, [torch.Generator().manual_seed(s) for s in seeds])
    data = {"observation": obs, "action": action, "action_log_prob": log_prob.unsqueeze(-1), "loc": loc,
            "scale": scale}
    for key in ("advantage", "cost_advantage", "value_target", "cost_value_target"):
        data[key] = torch.randn(2, size, 1, generator=generator)
    data["advantage"][1] = 0.0
    data["cost_advantage"][1] = 0.0
    if nan_seed is not None:
        data["advantage"][nan_seed, 7] = float("nan")
    return update, data


def seed_state(update, seed: int) -> list[torch.Tensor]:
    """Seed ``seed``'s parameters, Adam moments and step counts, as copies."""
    optimizer = update.parts.optimizer
    out = [t[seed].clone() for t in update.parts.model.flat_groups]
    for state in optimizer.state:
        out += [state["step"][seed].clone(), *(t[seed].clone() for t in state["exp_avg"] + state["exp_avg_sq"])]
    return out


def test_a_seed_whose_kl_stop_fired_does_not_move_for_the_rest_of_the_epoch():
    lam, violation, active = torch.zeros(2), torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.bool)
    stopped_early, data = synthetic_update(passes=1, target_kl=1e-7)
    stopped_early(data, lam, violation, active)
    full, data = synthetic_update(passes=4, target_kl=1e-7)
    result = full(data, lam, violation, active)
    assert result.metrics["Train/StopIter"].tolist() == [1.0, 4.0]  # seed 0's KL exceeded 1e-7, seed 1's stayed 0
    assert result.metrics["Train/KL"][0] > 1e-7 and result.metrics["Train/KL"][1] == 0
    for mine, after_one_pass in zip(seed_state(full, 0), seed_state(stopped_early, 0)):
        assert torch.equal(mine, after_one_pass)  # parameters, moments, step counts: untouched after its stop
    assert full.parts.shuffler.generators[0].get_state().equal(stopped_early.parts.shuffler.generators[0].get_state())
    assert not torch.equal(full.parts.model.flat_critics[1], stopped_early.parts.model.flat_critics[1])
    assert full.parts.optimizer.state[1]["step"].tolist() == [8.0, 32.0]


def test_a_seed_whose_update_turns_non_finite_is_put_back_and_flagged():
    lam, violation, active = torch.zeros(2), torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.bool)
    clean, data = synthetic_update(passes=3, target_kl=1.0)
    clean(data, lam, violation, active)
    broken, data = synthetic_update(passes=3, target_kl=1.0, nan_seed=0)
    before = seed_state(broken, 0)
    result = broken(data, lam, violation, active)
    assert result.diverged.tolist() == [True, False]
    for restored, saved in zip(seed_state(broken, 0), before):
        assert torch.equal(restored, saved)
    for mine, alone in zip(seed_state(broken, 1), seed_state(clean, 1)):
        torch.testing.assert_close(mine, alone, rtol=1e-6, atol=0)


def test_a_diverged_seed_is_frozen_and_reported_while_the_others_train_on(tmp_path, capsys):
    cfg = group_config(tmp_path / "nan", [0, 1, 2], total_steps=1200)
    broken = OnPolicyGroupTrainer(cfg)
    batches = recording(broken)
    broken.run(max_epochs=1)
    with torch.no_grad():
        broken.model.flat_actor[1, 0] = float("nan")  # seed 1 diverges between epochs 1 and 2
    metrics = broken.run()
    assert "seed 1 diverged in epoch 2" in capsys.readouterr().err
    assert torch.equal(batches[1]["action"][2:4], torch.zeros_like(batches[1]["action"][2:4]))  # idles
    assert len(progress(cfg.seed_dir(1))) == 1
    summary = json.loads((cfg.seed_dir(1) / "summary.json").read_text())
    assert summary["Diverged"] is True and summary["DivergedEpoch"] == 2
    assert json.loads((cfg.run_dir / "summary.json").read_text())["diverged"] == [1]
    assert metrics["seed-001/Diverged"] is True and metrics["Train/Epoch"] == 3

    clean = OnPolicyGroupTrainer(group_config(tmp_path / "clean", [0, 1, 2], total_steps=1200))
    clean.run()
    for seed in (0, 2):
        rows, expected = without_times(progress(cfg.seed_dir(seed))), without_times(progress(clean.cfg.seed_dir(seed)))
        assert len(rows) == len(expected) == 3
        for row, reference in zip(rows, expected):
            for name in reference:
                assert float(row[name]) == pytest.approx(float(reference[name]), rel=1e-6, nan_ok=True), name


# --------------------------------------------------------------------------- resume
@pytest.mark.parametrize("algo", ["ppo_lag", "cup", "cpo"])
def test_resume_continues_the_group_bit_for_bit(tmp_path, algo):
    uninterrupted = OnPolicyGroupTrainer(group_config(tmp_path / "a", [0, 1], algo=algo, total_steps=1200))
    uninterrupted.run()

    first = OnPolicyGroupTrainer(group_config(tmp_path / "b", [0, 1], algo=algo, total_steps=1200))
    first.run(max_epochs=1)
    checkpoint = OnPolicyGroupTrainer.load_checkpoint(first.cfg.run_dir)
    resumed = OnPolicyGroupTrainer(group_config(tmp_path / "b", [0, 1], algo=algo, total_steps=1200), checkpoint)
    assert resumed.epoch == 1
    resumed.run()

    for mine, theirs in zip(resumed.model.flat_groups, uninterrupted.model.flat_groups):
        assert torch.equal(mine, theirs)
    assert torch.equal(resumed.obs_norm.mean, uninterrupted.obs_norm.mean)
    for seed in (0, 1):
        rows = without_times(progress(resumed.cfg.seed_dir(seed)))
        assert len(rows) == 3 and rows == without_times(progress(uninterrupted.cfg.seed_dir(seed)))
    entry = seed_entry(checkpoint, 1)
    assert entry["config"]["seed"] == 1 and set(entry["networks"]) == {"actor", "critic", "cost_critic"}


# --------------------------------------------------------------------------- table and command line
@pytest.mark.parametrize("algo", sorted(ALGORITHM_NAMES))
def test_every_group_algorithm_trains_an_epoch(tmp_path, algo):
    group = OnPolicyGroupTrainer(group_config(tmp_path, [0, 1], algo=algo))
    before = [t.clone() for t in group.model.flat_groups]
    metrics = group.train_epoch()
    assert all(not torch.equal(a, b) for a, b in zip(before, group.model.flat_groups))
    for run in group.runs:
        assert all(value == value for value in run.last_row.values()), run.last_row  # no NaN: episodes finished
    assert metrics["Train/Epoch"] == 1  # the progress bar's figures: the seeds' mean row


TINY = ["--env-id", POINT, "--env-options", "max_episode_steps=100", "--num-envs", "2", "--steps-per-epoch", "200",
        "--total-steps", "400", "--update-iters", "2", "--eval-episodes", "1", "--wandb", "disabled",
        "--progress", "false"]


def test_command_line_group_writes_every_per_seed_file(tmp_path, capsys):
    assert main(["--seeds", "0", "1", "--algo", "ppo_lag", "--output-dir", str(tmp_path), *TINY]) == 0
    group_dir = tmp_path / POINT / "ppo_lag" / "seeds-0-1"
    for name in (CHECKPOINT_NAME, "config.json", "summary.json", "curves.png"):  # curves.png: every seed and the mean
        assert (group_dir / name).exists(), name
    for seed in (0, 1):
        for name in ("progress.csv", "config.json", "summary.json", "curves.png", "csv"):
            assert (group_dir / f"seed-{seed:03d}" / name).exists(), (seed, name)
        assert "Metrics/EvalEpRet" in json.loads((group_dir / f"seed-{seed:03d}" / "summary.json").read_text())
    out = capsys.readouterr().out
    assert "seed 0: training EpRet" in out and "seed 1: training EpRet" in out and "mean of the seeds" in out

    assert main(["--seeds", "0", "1", "--output-dir", str(tmp_path), *TINY]) == 2  # never over a group unasked
    assert "already holds a run" in capsys.readouterr().err
    assert main(["--resume", str(group_dir), "--seeds", "0", "2"]) == 2
    assert "keeps its seeds" in capsys.readouterr().err
    assert main(["--resume", str(group_dir), "--total-steps", "600"]) == 0
    assert epochs(group_dir / "seed-001") == [1, 2, 3]
    assert main(["--seeds", "0", "1", "--overwrite", "--output-dir", str(tmp_path), *TINY]) == 0
    assert epochs(group_dir / "seed-001") == [1, 2]


def test_command_line_second_order_group_writes_every_per_seed_file(tmp_path):
    assert main(["--seeds", "0", "1", "--algo", "cpo", "--output-dir", str(tmp_path), *TINY]) == 0
    group_dir = tmp_path / POINT / "cpo" / "seeds-0-1"
    for name in (CHECKPOINT_NAME, "config.json", "summary.json"):
        assert (group_dir / name).exists(), name
    for seed in (0, 1):
        for name in ("progress.csv", "config.json", "summary.json", "curves.png", "csv"):
            assert (group_dir / f"seed-{seed:03d}" / name).exists(), (seed, name)
        assert "Metrics/EvalEpRet" in json.loads((group_dir / f"seed-{seed:03d}" / "summary.json").read_text())
        assert epochs(group_dir / f"seed-{seed:03d}") == [1, 2]
        assert [row["Train/StopIter"] for row in progress(group_dir / f"seed-{seed:03d}") if row["Train/Epoch"]] \
            == ["2", "2"]  # every critic pass, as an integer like the single-seed run's


def test_the_config_takes_second_order_groups():
    for algo in ("npg", "trpo", "trpo_lag", "rcpo", "cpo", "pcpo"):
        cfg = TrainConfig(algo=algo, seeds=[0, 1], env_id=POINT)
        assert cfg.group and cfg.second_order and algo in ALGORITHM_NAMES


def test_the_config_takes_pixel_groups():  # stacked CNN encoders: tests/test_train_vision.py
    cfg = TrainConfig(seeds=[0, 1], env_id="SafetyPointGoal1Vision-v0")
    assert cfg.group and cfg.observation_mode != "vector"


@pytest.mark.parametrize("flags, message", [
    (["--seeds", "0", "0"], "seeds must be distinct"),
    (["--seeds", "0", "-1"], "seeds must be >= 0"),
    (["--seeds", "0", "1", "--seed", "0"], "--seed and --seeds cannot be given together"),
    (["--seeds", "0", "--algo", "mappo", "--env-id", CHEETAH], "multi-agent algorithm"),  # groups take it, not this env
])
def test_bad_seed_groups_exit_2_with_a_message(tmp_path, capsys, flags, message):
    assert main([*flags, "--output-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "sg-train: error:" in err and message in err


def test_wandb_offline_gives_each_seed_its_own_run(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    flags = [flag if flag != "disabled" else "offline" for flag in TINY]
    assert main(["--seeds", "0", "1", "--eval-episodes", "0", "--output-dir", str(tmp_path), *flags]) == 0
    for seed in (0, 1):
        runs = list((tmp_path / POINT / "ppo_lag" / "seeds-0-1" / f"seed-{seed:03d}" / "wandb").glob("offline-run-*"))
        assert len(runs) == 1 and any(runs[0].glob("*.wandb"))
