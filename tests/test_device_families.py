"""``--device`` for the multi-agent and off-policy families (``sg_torchrl.train.devices``).

What is checked, on any machine:

* every family's config takes any device name (a saved config reads anywhere); a CUDA device this
  machine lacks is refused where training starts, with a message naming it, before anything is built;
* the multi-agent round reads nothing back to the host per minibatch: one epoch's host reads are as
  many with 8 minibatches per pass as with 2 (MAPPO-Lag, MACPO), while a read added per optimiser step
  shows up;
* an off-policy gradient step reads nothing back to the host (the replay buffers, which live there, aside),
  while a read added per optimiser step shows up;
* checkpoints hold CPU tensors only, and a run whose saved config names CUDA continues with
  ``--device cpu``.

With CUDA (skipped elsewhere): a multi-agent and an off-policy group on ``cuda`` with every parameter,
Adam moment, PopArt statistic and multiplier there; their update on the CPU run's batch (multi-agent) or
replay (off-policy) agrees with the CPU's within a tolerance; their checkpoint continues on the CPU; and
the synchronising calls do not grow with the minibatches (multi-agent) or the gradient steps (off-policy).
"""

from __future__ import annotations

import json

import pytest
import torch

torch.set_num_threads(1)

from sg_torchrl.train import MultiAgentGroupTrainer, OffPolicyGroupTrainer, TrainConfig, main  # noqa: E402
from sg_torchrl.train.checkpoint import CHECKPOINT_NAME, load_checkpoint, save_checkpoint  # noqa: E402
from sg_torchrl.train.replay import SeedReplay  # noqa: E402
from sg_torchrl.train.seed_adam import SeedMaskedAdam  # noqa: E402
from device_checks import counting_host_reads, only_within, synchronising_calls, tensors  # noqa: E402

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
TEAM_ENV, SINGLE_ENV = "Safety2x3HalfCheetahVelocity-v0", "SafetyHalfCheetahVelocity-v1"


def team_config(tmp_path, **overrides) -> TrainConfig:
    """MAPPO-Lag on 2x3 HalfCheetah, two seeds, one 200-step epoch per seed (100-step episodes, costs from the start)."""
    values = dict(algo="mappo_lag", env_id=TEAM_ENV, env_options={"max_episode_steps": 100, "velocity_threshold": 0.5},
                  num_envs=2, steps_per_epoch=200, total_steps=200, update_iters=2, hidden_sizes=[16, 16],
                  cost_limit=0.0, eval_episodes=0, wandb="disabled", progress=False, output_dir=str(tmp_path),
                  seeds=[0, 1], checkpoint_every=100)
    values.update(overrides)
    return TrainConfig(**values)


def replay_config(tmp_path, **overrides) -> TrainConfig:
    """SAC-Lag on HalfCheetah, two seeds, 200-step epochs from 2 simulators, 100 warm-up steps, small networks."""
    values = dict(algo="sac_lag", env_id=SINGLE_ENV, env_options={"max_episode_steps": 50, "velocity_threshold": 0.5},
                  num_envs=2, steps_per_epoch=200, total_steps=200, warmup_steps=100, minibatch_size=16,
                  hidden_sizes=[16, 16], replay_size=1000, eval_episodes=0, wandb="disabled", progress=False,
                  output_dir=str(tmp_path), seeds=[0, 1], checkpoint_every=100)
    values.update(overrides)
    return TrainConfig(**values)


FLAGS = {
    "mappo_lag": ["--env-id", TEAM_ENV, "--env-options", "max_episode_steps=100", "--hidden-sizes", "16", "16"],
    "sac_lag": ["--env-id", SINGLE_ENV, "--env-options", "max_episode_steps=50", "--warmup-steps", "100",
                "--minibatch-size", "16", "--hidden-sizes", "16", "16", "--replay-size", "1000"],
}
COMMON = ["--num-envs", "2", "--steps-per-epoch", "200", "--total-steps", "200", "--eval-episodes", "0",
          "--wandb", "disabled", "--progress", "false", "--seeds", "0", "1"]


@pytest.fixture
def no_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


# --------------------------------------------------------------------------- configs and devices this machine lacks
@pytest.mark.parametrize("algo", ["mappo", "macpo", "sac_lag", "td3", "ddpg_pid"])
@pytest.mark.parametrize("device", ["cpu", "cuda", "cuda:1"])
def test_every_family_takes_any_device_in_its_config(algo, device):
    assert TrainConfig(algo=algo, device=device).device == device


@pytest.mark.parametrize("algo", ["mappo_lag", "sac_lag"])
def test_cuda_without_cuda_is_refused_before_anything_is_built(tmp_path, capsys, no_cuda, algo):
    assert main(["--algo", algo, "--output-dir", str(tmp_path), "--device", "cuda", *FLAGS[algo], *COMMON]) == 2
    err = capsys.readouterr().err
    assert "sg-train: error: config: device 'cuda' asks for CUDA" in err and "--device cpu" in err
    assert not any(tmp_path.iterdir())
    make = team_config if algo == "mappo_lag" else replay_config
    trainer = MultiAgentGroupTrainer if algo == "mappo_lag" else OffPolicyGroupTrainer
    with pytest.raises(ValueError, match="device 'cuda:0' asks for CUDA"):
        trainer(make(tmp_path, device="cuda:0"))
    assert not any(tmp_path.iterdir())


# --------------------------------------------------------------------------- host reads in the update path
def team_epoch_host_reads(tmp_path, monkeypatch, algo: str, minibatch_size: int):
    """The host reads of one multi-agent epoch (collection, GAEs, the round, the metrics, logs).

    200 samples per seed: minibatches of 100 make 2 per pass, of 25 make 8; a KL limit no seed reaches keeps
    every pass of MAPPO-Lag (MACPO's KL is its trust region, taken once per agent whatever the minibatches).
    """
    extra = {"target_kl": 1e9} if algo != "macpo" else {}
    trainer = MultiAgentGroupTrainer(team_config(tmp_path / f"{algo}-{minibatch_size}", algo=algo,
                                                 minibatch_size=minibatch_size, **extra))
    with counting_host_reads(monkeypatch) as counts:
        trainer.train_epoch()
    return counts


@pytest.mark.parametrize("algo", ["mappo_lag", "macpo"])
def test_the_multi_agent_round_reads_nothing_back_per_minibatch(tmp_path, monkeypatch, algo):
    few = team_epoch_host_reads(tmp_path, monkeypatch, algo, 100)
    many = team_epoch_host_reads(tmp_path, monkeypatch, algo, 25)
    assert sum(few.values()) > 0  # the once-per-pass and once-per-stage reads are seen
    assert many == few


def reading_every_adam_step(monkeypatch) -> None:
    """Make every ``SeedMaskedAdam`` step read one value back to the host: the counts below are not blind."""
    step = SeedMaskedAdam.step

    def reading_step(self, *args, **kwargs):
        self.state[0]["step"].sum().item()
        return step(self, *args, **kwargs)

    monkeypatch.setattr(SeedMaskedAdam, "step", reading_step)


def test_a_read_per_optimiser_step_of_the_round_would_be_seen(tmp_path, monkeypatch):
    reading_every_adam_step(monkeypatch)
    few = team_epoch_host_reads(tmp_path, monkeypatch, "mappo_lag", 100)
    many = team_epoch_host_reads(tmp_path, monkeypatch, "mappo_lag", 25)
    assert many["item"] - few["item"] == 2 * 2 * (8 - 2)  # one step for both seeds: 2 agents, 2 passes


def gradient_step_host_reads(tmp_path, monkeypatch):
    """The host reads inside one epoch's gradient steps, the replay buffers' sampling (on the host) left out,
    and the number of gradient steps taken."""
    trainer = OffPolicyGroupTrainer(replay_config(tmp_path))
    with counting_host_reads(monkeypatch) as counts:
        only_within(monkeypatch, counts, OffPolicyGroupTrainer, "_gradient_step", paused=((SeedReplay, "sample"),))
        trainer.train_epoch()
    return counts, trainer.gradient_steps


def test_an_off_policy_gradient_step_reads_nothing_back(tmp_path, monkeypatch):
    counts, steps = gradient_step_host_reads(tmp_path, monkeypatch)
    assert steps == 100  # one per env step per seed after the 100 warm-up steps
    assert sum(counts.values()) == 0, counts


def test_a_read_per_gradient_step_would_be_seen(tmp_path, monkeypatch):
    reading_every_adam_step(monkeypatch)
    counts, steps = gradient_step_host_reads(tmp_path, monkeypatch)
    delay = replay_config(tmp_path).policy_delay
    assert steps == 100 and delay > 1
    # the reward and cost critics every step, the actor every policy_delay steps
    assert counts["item"] == 2 * steps + steps // delay and sum(counts.values()) == counts["item"]


# --------------------------------------------------------------------------- checkpoints
@pytest.mark.parametrize("algo", ["mappo_lag", "sac_lag"])
def test_checkpoints_hold_cpu_tensors_and_a_cuda_run_continues_on_the_cpu(tmp_path, capsys, no_cuda, algo):
    assert main(["--algo", algo, "--output-dir", str(tmp_path), *FLAGS[algo], *COMMON]) == 0
    run_dir = next(tmp_path.glob(f"*/{algo}/seeds-0-1"))
    state = load_checkpoint(run_dir)
    assert all(t.device.type == "cpu" for t in tensors(state))
    state["config"]["device"] = "cuda"  # the run as a GPU machine would have written it
    save_checkpoint(state, run_dir / CHECKPOINT_NAME)
    assert main(["--resume", str(run_dir), "--total-steps", "400"]) == 2
    assert "device 'cuda' asks for CUDA" in capsys.readouterr().err
    assert main(["--resume", str(run_dir), "--total-steps", "400", "--device", "cpu"]) == 0
    assert json.loads((run_dir / "config.json").read_text())["device"] == "cpu"
    assert load_checkpoint(run_dir)["epoch"] == 2


# --------------------------------------------------------------------------- on a GPU
def continues_on_the_cpu(gpu, config: TrainConfig, state, epochs: int) -> None:
    """A cuda run's checkpoint holds CPU tensors; a trainer built from it on the CPU starts from the same
    ``state(trainer)`` and runs to ``epochs``."""
    checkpoint = type(gpu).load_checkpoint(gpu.cfg.run_dir)
    assert all(t.device.type == "cpu" for t in tensors(checkpoint))
    on_cpu = type(gpu)(config, checkpoint)
    for mine, theirs in zip(state(on_cpu), state(gpu), strict=True):
        assert torch.equal(mine, theirs.cpu())
    on_cpu.run()
    assert on_cpu.epoch == epochs


def round_state(trainer: MultiAgentGroupTrainer) -> list[torch.Tensor]:
    """Every tensor a multi-agent update moves: the stacks, Adam's moments and steps, PopArt, the multipliers."""
    rounds = trainer.round
    return [*trainer.networks.tensors(), *(t for group in rounds.exp_avg + rounds.exp_avg_sq for t in group),
            rounds.steps, *rounds.popart.values(),
            *(buffer for team in rounds.team_multipliers for buffer in team.buffers())]


@CUDA
@pytest.mark.parametrize("algo", ["mappo_lag", "macpo"])
def test_a_multi_agent_group_updates_on_cuda_as_on_the_cpu_and_continues_there(tmp_path, algo):
    cpu = MultiAgentGroupTrainer(team_config(tmp_path / "cpu", algo=algo, minibatch_size=50, total_steps=400))
    gpu = MultiAgentGroupTrainer(team_config(tmp_path / "gpu", algo=algo, minibatch_size=50, total_steps=400,
                                             device="cuda"))
    assert all(t.is_cuda for t in round_state(gpu)) and all(t.is_cuda for t in gpu.teams[0].networks.parameters())
    for mine, theirs in zip(round_state(cpu), round_state(gpu), strict=True):
        assert torch.equal(mine, theirs.cpu())  # the same initialisation on every device
    batch = cpu.collector.collect()  # one batch for both: the update alone is compared
    cpu._learn(batch.clone())
    rows, diverged = gpu._learn(batch.clone())
    assert not any(diverged) and all(row is not None for row in rows)
    assert all(t.is_cuda for t in round_state(gpu))
    for mine, theirs in zip(round_state(cpu), round_state(gpu), strict=True):
        torch.testing.assert_close(theirs.cpu(), mine, rtol=1e-3, atol=1e-4)
    gpu.run(max_epochs=1)  # a whole epoch on cuda: collection, update, checkpoint
    continues_on_the_cpu(gpu, team_config(tmp_path / "gpu", algo=algo, minibatch_size=50, total_steps=400),
                         round_state, epochs=2)


@CUDA
def test_the_cuda_round_synchronises_no_more_with_more_minibatches(tmp_path):
    def calls(minibatch_size: int) -> int:
        trainer = MultiAgentGroupTrainer(team_config(tmp_path / str(minibatch_size), minibatch_size=minibatch_size,
                                                     target_kl=1e9, device="cuda"))
        return synchronising_calls(trainer.train_epoch)

    assert calls(25) == calls(100)


def replay_state(trainer: OffPolicyGroupTrainer) -> list[torch.Tensor]:
    """Every tensor an off-policy step moves: the rows, the targets, Adam's moments and steps."""
    return [*trainer.nets.trained().values(), *trainer.nets.targets().values(),
            *(t for opt in trainer.optimizers.values() for state in opt.state
              for t in (state["step"], *state["exp_avg"], *state["exp_avg_sq"]))]


@CUDA
@pytest.mark.parametrize("algo", ["sac_lag", "td3_lag"])
def test_an_off_policy_group_steps_on_cuda_as_on_the_cpu_and_continues_there(tmp_path, algo):
    # the first epoch is all warm-up (random actions from the CPU generators): both replays hold the same rows
    options = dict(algo=algo, warmup_steps=200, total_steps=400)
    cpu = OffPolicyGroupTrainer(replay_config(tmp_path / "cpu", **options))
    gpu = OffPolicyGroupTrainer(replay_config(tmp_path / "gpu", **options, device="cuda"))
    cpu.train_epoch()
    gpu.train_epoch()
    assert gpu.gradient_steps == cpu.gradient_steps == 0
    for mine, theirs in zip(replay_state(cpu), replay_state(gpu), strict=True):
        assert torch.equal(mine, theirs.cpu())
    for _ in range(20):
        cpu._gradient_step(cpu.nets)
        gpu._gradient_step(gpu.nets)
    assert all(t.is_cuda for t in replay_state(gpu)) and gpu.lam.is_cuda
    assert all(t.is_cuda for t in gpu.sums.values())
    for mine, theirs in zip(replay_state(cpu), replay_state(gpu), strict=True):
        torch.testing.assert_close(theirs.cpu(), mine, rtol=1e-3, atol=1e-4)
    for name in gpu.sums:
        torch.testing.assert_close(gpu.sums[name].cpu(), cpu.sums[name], rtol=1e-3, atol=1e-4)
    gpu.run()  # the second epoch on cuda, gradient steps inside collection, then the checkpoint
    continues_on_the_cpu(gpu, replay_config(tmp_path / "gpu", **{**options, "total_steps": 600}), replay_state,
                         epochs=3)


@CUDA
def test_cuda_gradient_steps_synchronise_no_more_with_more_steps(tmp_path):
    trainer = OffPolicyGroupTrainer(replay_config(tmp_path, warmup_steps=200, total_steps=400, device="cuda"))
    trainer.train_epoch()  # fills the replay buffers

    def steps(count: int):
        return lambda: [trainer._gradient_step(trainer.nets) for _ in range(count)]

    assert synchronising_calls(steps(20)) == synchronising_calls(steps(5))
