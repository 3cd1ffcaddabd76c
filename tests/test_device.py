"""``--device``: where a single-agent run's networks and updates live (``sg_torchrl.train.devices``).

The multi-agent and off-policy families' device checks are ``tests/test_device_families.py``.

What is checked, on any machine:

* ``--device cpu`` given explicitly trains exactly as the default (checkpointed parameters, progress
  rows but their times), and ``config.json`` records the device;
* the update path reads nothing back to the host per minibatch: the calls that copy a tensor to
  Python (``.item()``, ``.tolist()``, ``.cpu()``, ``.numpy()``, ``float()``, ``int()``, ``bool()``)
  made by one epoch are counted, and they are as many with 8 minibatches per pass as
  with 2 (first order, CUP's two stages, second order), while a read added per minibatch shows up;
* a device this machine lacks is refused with a message naming it (exit status 2 from ``sg-train``,
  ``ValueError`` from the Python API), and a bad name is refused;
* checkpoints hold CPU tensors only and load on the CPU; a run whose saved config names CUDA is
  refused on a machine without it unless continued with ``--device cpu``, which then trains on.

With CUDA (skipped elsewhere): one epoch of a group of two on ``cuda`` with every parameter and
Adam moment there, its checkpoint continued on the CPU, and ``torch.cuda.set_sync_debug_mode``'s
count of synchronising calls the same for 2 and 8 minibatches per pass.
"""

from __future__ import annotations

import collections
import csv
import json

import pytest
import torch

torch.set_num_threads(1)

from sg_torchrl.train import OnPolicyGroupTrainer, TrainConfig, main  # noqa: E402
from sg_torchrl.train.checkpoint import CHECKPOINT_NAME, load_checkpoint, save_checkpoint  # noqa: E402
from sg_torchrl.train.devices import check_device_available  # noqa: E402
from sg_torchrl.train.group_updates import MaskedSeedStep  # noqa: E402
from device_checks import counting_host_reads, synchronising_calls, tensors  # noqa: E402

CHEETAH = "SafetyHalfCheetahVelocity-v1"
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def group_config(tmp_path, **overrides) -> TrainConfig:
    """PPO-Lag on HalfCheetah, two seeds, one 256-step epoch per seed (100-step episodes, costs from the start)."""
    values = dict(
        env_id=CHEETAH, env_options={"max_episode_steps": 100, "velocity_threshold": 0.5}, num_envs=2,
        steps_per_epoch=256, total_steps=256, update_iters=2, minibatch_size=64, cost_limit=0.0, eval_episodes=0,
        wandb="disabled", progress=False, output_dir=str(tmp_path), seeds=[0, 1], checkpoint_every=100,
    )
    values.update(overrides)
    return TrainConfig(**values)


def without_times(path) -> list[dict[str, str]]:
    with open(path) as f:
        return [{k: v for k, v in row.items() if not k.startswith("Time/")} for row in csv.DictReader(f)]


# --------------------------------------------------------------------------- cpu, explicitly
TINY = ["--env-id", CHEETAH, "--env-options", "max_episode_steps=100", "--num-envs", "2", "--steps-per-epoch", "200",
        "--total-steps", "400", "--update-iters", "2", "--eval-episodes", "0", "--wandb", "disabled",
        "--progress", "false", "--seeds", "0", "1"]


def test_device_cpu_given_explicitly_trains_as_the_default(tmp_path):
    assert main(["--output-dir", str(tmp_path / "default"), *TINY]) == 0
    assert main(["--output-dir", str(tmp_path / "cpu"), "--device", "cpu", *TINY]) == 0
    runs = {name: tmp_path / name / CHEETAH / "ppo_lag" / "seeds-0-1" for name in ("default", "cpu")}
    assert json.loads((runs["cpu"] / "config.json").read_text())["device"] == "cpu"
    assert json.loads((runs["default"] / "seed-001" / "config.json").read_text())["device"] == "cpu"
    checkpoints = {name: load_checkpoint(run) for name, run in runs.items()}
    for mine, theirs in zip(checkpoints["cpu"]["seeds"], checkpoints["default"]["seeds"], strict=True):
        for name in ("actor", "critic", "cost_critic"):
            for key, value in mine["networks"][name].items():
                assert torch.equal(value, theirs["networks"][name][key]), (name, key)
    for seed in ("seed-000", "seed-001"):
        rows = without_times(runs["cpu"] / seed / "progress.csv")
        assert len(rows) == 2 and rows == without_times(runs["default"] / seed / "progress.csv")


# --------------------------------------------------------------------------- host reads in the update path
def epoch_host_reads(tmp_path, monkeypatch, algo: str, minibatch_size: int) -> collections.Counter[str]:
    """The host reads of one epoch of ``algo`` (collection, multipliers, GAE, the group update, the metrics, logs).

    Collection is the same whatever the minibatch size, and a KL limit no seed reaches keeps every
    pass, so two minibatch sizes' counts differ only by what the minibatch steps read.
    """
    cfg = group_config(tmp_path / f"{algo}-{minibatch_size}", algo=algo, minibatch_size=minibatch_size,
                       target_kl=1e9)
    trainer = OnPolicyGroupTrainer(cfg)
    with counting_host_reads(monkeypatch) as counts:
        trainer.train_epoch()
    return counts


@pytest.mark.parametrize("algo", ["ppo_lag", "cup", "trpo_lag"])
def test_the_update_reads_nothing_back_per_minibatch(tmp_path, monkeypatch, algo):
    # 256 samples per seed: minibatches of 128 make 2 per pass, of 32 make 8 (CUP: 2 vs 8 in each stage)
    few = epoch_host_reads(tmp_path, monkeypatch, algo, 128)
    many = epoch_host_reads(tmp_path, monkeypatch, algo, 32)
    assert sum(few.values()) > 0  # the once-per-pass and once-per-epoch reads are seen
    assert many == few


def test_a_read_per_minibatch_would_be_seen(tmp_path, monkeypatch):
    """The count above is not blind: one ``.item()`` added to the minibatch step grows it with the minibatches."""
    step = MaskedSeedStep.__call__

    def reading_step(self, minibatch):
        out = step(self, minibatch)
        out[0]["losses"].sum().item()
        return out

    monkeypatch.setattr(MaskedSeedStep, "__call__", reading_step)
    few = epoch_host_reads(tmp_path, monkeypatch, "ppo_lag", 128)
    many = epoch_host_reads(tmp_path, monkeypatch, "ppo_lag", 32)
    assert many["item"] - few["item"] == 2 * (8 - 2)  # two passes, six more minibatches each


# --------------------------------------------------------------------------- devices this machine lacks
@pytest.fixture
def no_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def test_cuda_without_cuda_is_refused_on_the_command_line(tmp_path, capsys, no_cuda):
    assert main(["--output-dir", str(tmp_path), "--device", "cuda", *TINY]) == 2
    err = capsys.readouterr().err
    assert "sg-train: error: config: device 'cuda' asks for CUDA" in err and "--device cpu" in err
    assert not (tmp_path / CHEETAH).exists()  # refused before anything was built or written


def test_cuda_without_cuda_is_refused_by_the_python_api(tmp_path, no_cuda):
    cfg = group_config(tmp_path, device="cuda:0")  # the config itself is valid: it may be read on any machine
    with pytest.raises(ValueError, match="device 'cuda:0' asks for CUDA"):
        OnPolicyGroupTrainer(cfg)


def test_a_cuda_index_the_machine_lacks_is_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError, match=r"asks for CUDA device 2, but this machine has 1 \(cuda:0\)"):
        check_device_available("cuda:2")


@pytest.mark.parametrize("name", ["gpu", "cuda:", "cuda:x", "CPU", "mps"])
def test_bad_device_names_exit_2(tmp_path, capsys, name):
    assert main(["--output-dir", str(tmp_path), "--device", name, *TINY]) == 2
    assert "config: device must be one of cpu, cuda, cuda:N" in capsys.readouterr().err


def test_env_options_cannot_place_the_simulators():
    with pytest.raises(ValueError, match="env_options cannot set device: the simulators run on their backend"):
        TrainConfig(env_options={"device": "cuda"})


# --------------------------------------------------------------------------- checkpoints
def test_checkpoints_hold_cpu_tensors_and_a_cuda_run_continues_on_the_cpu(tmp_path, capsys, no_cuda):
    assert main(["--output-dir", str(tmp_path), *TINY]) == 0
    run_dir = tmp_path / CHEETAH / "ppo_lag" / "seeds-0-1"
    state = load_checkpoint(run_dir)
    assert all(t.device.type == "cpu" for t in tensors(state))
    # The run as a GPU machine would have written it: its saved config names CUDA.
    state["config"]["device"] = "cuda"
    save_checkpoint(state, run_dir / CHECKPOINT_NAME)
    assert main(["--resume", str(run_dir), "--total-steps", "600"]) == 2
    assert "device 'cuda' asks for CUDA" in capsys.readouterr().err
    assert main(["--resume", str(run_dir), "--total-steps", "600", "--device", "cpu"]) == 0
    assert json.loads((run_dir / "config.json").read_text())["device"] == "cpu"
    assert [row["Train/Epoch"] for row in without_times(run_dir / "seed-000" / "progress.csv")] == ["1", "2", "3"]


# --------------------------------------------------------------------------- on a GPU
@CUDA
def test_a_group_trains_an_epoch_on_cuda_and_continues_on_the_cpu(tmp_path):
    trainer = OnPolicyGroupTrainer(group_config(tmp_path, device="cuda", total_steps=512))
    trainer.run(max_epochs=1)
    assert all(t.is_cuda for t in trainer.model.parameters())
    assert all(t.is_cuda and t.grad.is_cuda for t in trainer.model.flat_groups)
    for state in trainer.optimizer.state:
        assert state["step"].is_cuda and all(t.is_cuda for t in state["exp_avg"] + state["exp_avg_sq"])
    assert all(torch.isfinite(t).all() for t in trainer.model.flat_groups)
    checkpoint = OnPolicyGroupTrainer.load_checkpoint(trainer.cfg.run_dir)
    assert all(t.device.type == "cpu" for t in tensors(checkpoint))
    on_cpu = OnPolicyGroupTrainer(group_config(tmp_path, device="cpu", total_steps=512), checkpoint)
    for cpu, cuda in zip(on_cpu.model.flat_groups, trainer.model.flat_groups):
        assert torch.equal(cpu, cuda.cpu())
    on_cpu.run()
    assert on_cpu.epoch == 2


def epoch_synchronising_calls(tmp_path, algo: str, minibatch_size: int) -> int:
    """Synchronising CUDA calls of one epoch on ``cuda`` (as :func:`epoch_host_reads`)."""
    cfg = group_config(tmp_path / f"{algo}-{minibatch_size}", algo=algo, minibatch_size=minibatch_size,
                       target_kl=1e9, device="cuda")
    return synchronising_calls(OnPolicyGroupTrainer(cfg).train_epoch)


@CUDA
@pytest.mark.parametrize("algo", ["ppo_lag", "trpo_lag"])
def test_the_cuda_update_synchronises_no_more_with_more_minibatches(tmp_path, algo):
    assert epoch_synchronising_calls(tmp_path, algo, 32) == epoch_synchronising_calls(tmp_path, algo, 128)
