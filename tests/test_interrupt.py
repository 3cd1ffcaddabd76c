"""Ctrl-C / SIGTERM: a run stops after the epoch under way, checkpointed, and resumes bit-identically."""

from __future__ import annotations

import signal
import threading

import pytest
import torch

torch.set_num_threads(1)

from sg_torchrl.train import MultiAgentGroupTrainer, OnPolicyGroupTrainer, SeedGroupTrainer, TrainingInterrupted, main  # noqa: E402
from sg_torchrl.train.interrupt import StopRequests  # noqa: E402
from trainer_checks import flat_parameters, tiny_config  # noqa: E402


def send_to_this_thread(signum: int) -> None:
    """Signal the calling (main) thread; its Python handler has run when this returns.

    ``os.kill(os.getpid(), ...)`` may deliver to another thread of the process and return before the
    handler runs, so a check right after it could see no request yet.
    """
    signal.pthread_kill(threading.get_ident(), signum)


def signal_during_epoch(trainer: SeedGroupTrainer, epoch: int, *signums: int) -> None:
    """Make ``trainer`` send itself ``signums`` at the start of its epoch number ``epoch`` (1-based)."""
    train_epoch = trainer.train_epoch

    def train_epoch_with_signals() -> dict[str, float]:
        if trainer.epoch + 1 == epoch:
            for signum in signums:
                send_to_this_thread(signum)
        return train_epoch()

    trainer.train_epoch = train_epoch_with_signals


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_after_the_epoch_and_resuming_is_exact(tmp_path, signum):
    uninterrupted = OnPolicyGroupTrainer(tiny_config(tmp_path / "a"))
    uninterrupted.run()

    interrupted = OnPolicyGroupTrainer(tiny_config(tmp_path / "b"))
    signal_during_epoch(interrupted, 2, signum)
    with pytest.raises(TrainingInterrupted) as stop:
        interrupted.run()
    assert (stop.value.epoch, stop.value.signum, stop.value.exit_code) == (2, signum, 128 + signum)
    assert stop.value.checkpoint == interrupted.checkpoint_path
    checkpoint = OnPolicyGroupTrainer.load_checkpoint(interrupted.checkpoint_path)
    assert checkpoint["epoch"] == 2  # the epoch under way finished; checkpoint_every (100) did not apply

    resumed = OnPolicyGroupTrainer(tiny_config(tmp_path / "b"), checkpoint)
    resumed.run()
    assert torch.equal(flat_parameters(uninterrupted), flat_parameters(resumed))
    assert (tmp_path / "b" / "run" / "summary.json").exists()


def test_multi_agent_runs_stop_the_same_way(tmp_path):
    cfg = tiny_config(tmp_path, algo="mappo_lag", env_id="Safety2x3HalfCheetahVelocity-v0", num_envs=1,
                      steps_per_epoch=1000, total_steps=2000, hidden_sizes=[32, 32])
    trainer = MultiAgentGroupTrainer(cfg)
    signal_during_epoch(trainer, 1, signal.SIGTERM)
    with pytest.raises(TrainingInterrupted) as stop:
        trainer.run()
    assert stop.value.epoch == 1
    assert MultiAgentGroupTrainer.load_checkpoint(trainer.checkpoint_path)["epoch"] == 1


@pytest.fixture
def python_sigint_handler():
    """SIGINT handled by Python's ``default_int_handler`` (``KeyboardInterrupt``) during the test.

    Python installs it at start-up only when SIGINT is not ignored; a process started in the
    background by a non-interactive shell (``make test &``, nohup) inherits SIGINT ignored, and
    then the "previous handler" a second signal falls back to ignores it too.
    """
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_a_second_signal_stops_at_once_without_a_checkpoint(tmp_path, python_sigint_handler):
    trainer = OnPolicyGroupTrainer(tiny_config(tmp_path))
    signal_during_epoch(trainer, 2, signal.SIGINT, signal.SIGINT)
    with pytest.raises(KeyboardInterrupt) as stop:
        trainer.run()
    assert not isinstance(stop.value, TrainingInterrupted)
    assert trainer.epoch == 1
    # No checkpoint of the interrupted epoch: the one on disk is the first epoch's (always written).
    assert OnPolicyGroupTrainer.load_checkpoint(trainer.checkpoint_path)["epoch"] == 1


def test_the_previous_handlers_come_back(tmp_path):
    before = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    OnPolicyGroupTrainer(tiny_config(tmp_path)).run(max_epochs=1)
    with StopRequests() as stop:
        assert signal.getsignal(signal.SIGINT) != before[signal.SIGINT]
        send_to_this_thread(signal.SIGTERM)
        assert stop.signum == signal.SIGTERM
        assert signal.getsignal(signal.SIGTERM) == before[signal.SIGTERM]  # restored by the first signal
    assert {signum: signal.getsignal(signum) for signum in before} == before


def test_sg_train_exits_with_the_signal_code_and_says_how_to_resume(tmp_path, monkeypatch, capsys):
    # The loop every trainer shares stops the same way, whichever trainer the command line picks.
    train_epoch = SeedGroupTrainer.train_epoch

    def train_epoch_with_sigterm(self) -> dict[str, float]:
        if self.epoch == 0:
            send_to_this_thread(signal.SIGTERM)
        return train_epoch(self)

    monkeypatch.setattr(SeedGroupTrainer, "train_epoch", train_epoch_with_sigterm)
    argv = ["--env-id", "SafetyHalfCheetahVelocity-v1", "--num-envs", "2", "--steps-per-epoch", "200",
            "--total-steps", "600", "--update-iters", "1", "--eval-episodes", "0", "--wandb", "disabled",
            "--progress", "false", "--output-dir", str(tmp_path), "--run-name", "run"]
    assert main(argv) == 128 + signal.SIGTERM
    err = capsys.readouterr().err
    assert "SIGTERM received" in err and "stopped after epoch 1" in err
    assert f"sg-train --resume {tmp_path / 'run'}" in err
    assert OnPolicyGroupTrainer.load_checkpoint(tmp_path / "run")["epoch"] == 1
