"""``sg-train``: typed config, the on-policy safe training loops, logging and checkpoints.

Run ``sg-train --help`` (or ``python -m sg_torchrl.train --help``) for every option. Every run trains on
one engine, :class:`~sg_torchrl.train.trainer.SeedGroupTrainer`: S >= 1 seeds of one algorithm side by
side in one process, one seed (``--seed s``) written in a single run's layout, a seed group
(``--seeds 0 1 2``) in the group's (the config picks the layout: :mod:`sg_torchrl.train.seed_runs`).
:func:`trainer_class` picks the algorithm family's subclass:

* the single-agent on-policy algorithms, flat-vector or pixel observations:
  :class:`~sg_torchrl.train.seed_group.OnPolicyGroupTrainer` (stacked networks, CNN encoders for pixels,
  one fused minibatch step); the algorithm is the TorchRL ``LossModule`` users compose in their own code
  (``PPOLagLoss``, ...), in the seed-batched form it defines;
* the four multi-agent algorithms (``--algo mappo``, ``happo``, ``mappo_lag``, ``macpo`` on a multi-agent
  env id): :class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer` (one team per seed);
* the off-policy algorithms (SAC, TD3, DDPG and their -Lag / -PID rows):
  :class:`~sg_torchrl.train.off_policy.OffPolicyGroupTrainer`.

``GroupTrainer``, the on-policy family's earlier name, still imports from here, with a
``DeprecationWarning`` (:data:`_DEPRECATED`).

``--resume`` continues a run; a checkpoint of the retired ``LossModule`` trainer (``--engine loss-module``
in earlier versions) is refused (:func:`refuse_retired_checkpoint`), saying how to go on.
Ctrl-C (or ``SIGTERM``) stops a run after the epoch under way, checkpointed; ``--resume`` continues it.

``--device cuda`` (``TrainConfig.device``; :mod:`sg_torchrl.train.devices`) puts a run's networks, optimiser
state and updates on a GPU, for every family (the off-policy replay buffers stay on the host), while the
simulators stay on their backend; a machine without the device is refused with the option checks (exit
status 2).

Importing this package loads neither torch, TorchRL nor MuJoCo (seconds on a busy machine): ``main``
parses and checks the whole command line first, so a bad flag or option fails in about a second. The
trainers and the algorithm tables (:data:`_HEAVY`) are imported by their
first use (PEP 562); the functions below import what they need inside, once the command line is valid.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sg_torchrl.algorithms import manifest
from sg_torchrl.lazy import lazy_exports
from sg_torchrl.train.config import (
    MULTI_AGENT_ALGORITHM_NAMES,
    PRESETS,
    RETIRED_FIELDS,
    TrainConfig,
)
from sg_torchrl.train.command_line import command_line_values
from sg_torchrl.train.devices import check_device_available
from sg_torchrl.train.interrupt import TrainingInterrupted
from sg_torchrl.train.writes import EXIT_WRITE_FAILED, RunWriteError, make_dirs

if TYPE_CHECKING:
    from sg_torchrl.train.trainer import SeedGroupTrainer

#: Names exported from modules that load torch: name -> its module, imported on first access (PEP 562).
_HEAVY = {
    "ALGORITHMS": "sg_torchrl.train.algorithms",
    "MULTI_AGENT_ALGORITHMS": "sg_torchrl.train.multi_agent",
    "MultiAgentGroupTrainer": "sg_torchrl.train.multi_agent_group",
    "OffPolicyGroupTrainer": "sg_torchrl.train.off_policy",
    "OnPolicyGroupTrainer": "sg_torchrl.train.seed_group",
    "SeedGroupTrainer": "sg_torchrl.train.trainer",
}

#: Earlier names still importable from here, each with a ``DeprecationWarning``: old name -> current name.
_DEPRECATED = {"GroupTrainer": "OnPolicyGroupTrainer"}

_heavy_getattr, __dir__ = lazy_exports(__name__, _HEAVY)


def __getattr__(name: str) -> Any:
    """The names of :data:`_HEAVY`, imported on first use; a :data:`_DEPRECATED` name warns and gives its successor."""
    if name in _DEPRECATED:
        import warnings

        warnings.warn(f"sg_torchrl.train.{name} is now {_DEPRECATED[name]}; the old name will go in a later release",
                      DeprecationWarning, stacklevel=2)
        return _heavy_getattr(_DEPRECATED[name])
    return _heavy_getattr(name)


__all__ = [
    "ALGORITHMS", "MULTI_AGENT_ALGORITHMS", "PRESETS", "MultiAgentGroupTrainer", "OffPolicyGroupTrainer",
    "OnPolicyGroupTrainer", "SeedGroupTrainer", "TrainConfig", "TrainingInterrupted", "algorithm_title", "main",
    "refuse_retired_checkpoint", "train", "trainer_class",
]


def trainer_class(cfg: TrainConfig) -> type[SeedGroupTrainer]:
    """The engine's family subclass for ``cfg``'s algorithm: :class:`OffPolicyGroupTrainer`,
    :class:`MultiAgentGroupTrainer` or :class:`OnPolicyGroupTrainer`. One seed or a seed group is the
    config's layout (:func:`~sg_torchrl.train.seed_runs.run_layout`), which every family takes."""
    if cfg.off_policy:
        from sg_torchrl.train.off_policy import OffPolicyGroupTrainer

        return OffPolicyGroupTrainer
    if cfg.multi_agent:
        from sg_torchrl.train.multi_agent_group import MultiAgentGroupTrainer

        return MultiAgentGroupTrainer
    from sg_torchrl.train.seed_group import OnPolicyGroupTrainer

    return OnPolicyGroupTrainer


def refuse_retired_checkpoint(checkpoint: dict[str, Any], where: str | Path) -> None:
    """Refuse a checkpoint (:meth:`SeedGroupTrainer.load_checkpoint`'s dict, read from ``where``) of the retired
    ``LossModule`` trainer, which earlier versions ran for ``--engine loss-module`` and for pixel observations.

    Its checkpoints are a single-agent run's without a ``"seed_group"`` entry (those written before
    ``engine`` existed included); the seed-group engine cannot continue them (other networks, optimiser
    and random streams), so they are refused with what to do instead.

    Raises:
        CheckpointError: ``checkpoint`` is such a checkpoint.
    """
    from sg_torchrl.train.checkpoint import CheckpointError

    config = checkpoint.get("config", {})
    if config.get("algo") in MULTI_AGENT_ALGORITHM_NAMES or "seed_group" in checkpoint:
        return
    raise CheckpointError(
        f"{where} was written by the LossModule trainer (engine {config.get('engine') or 'loss-module'}), which "
        f"this sg_torchrl no longer has: single-agent runs train on the seed-group engine, which cannot continue "
        f"it. Start it over with the same command and a fresh --run-name (or --overwrite in its directory), or "
        f"continue it with an earlier sg_torchrl release that still has --engine loss-module")


def algorithm_title(algo: str) -> str:
    """Display name of an ``--algo`` value (``"mappo_lag"`` -> ``"MAPPO-Lag"``): its manifest row's title."""
    return manifest.get(algo).title


def train(cfg: TrainConfig) -> dict[str, float]:
    """Run (or continue, when ``cfg.resume`` is set) one experiment; returns the final metrics.

    The trainer is :func:`trainer_class`'s.

    Raises:
        RunDirectoryError: a new run in a directory that already holds one, without ``cfg.overwrite``
            (checked before anything is built).
        CheckpointError: ``cfg.resume`` names a checkpoint that is damaged, not ours, or of the retired
            ``LossModule`` trainer (:func:`refuse_retired_checkpoint`).
        RunWriteError: a file of the run could not be written (a full disk, a read-only or vanished
            directory); the last checkpoint and the logs up to it are intact.
    """
    from sg_torchrl.train.checkpoint import check_new_run_dir

    from sg_torchrl.train.trainer import SeedGroupTrainer

    if cfg.resume:
        checkpoint = SeedGroupTrainer.load_checkpoint(cfg.resume)
        refuse_retired_checkpoint(checkpoint, cfg.resume)
    else:
        check_new_run_dir(cfg.run_dir, cfg.overwrite)
        checkpoint = None
    return trainer_class(cfg)(cfg, checkpoint).run()


def _resolve_resume(argv: list[str]) -> TrainConfig:
    """The config of an ``sg-train`` command line.

    Without ``--resume``: the preset and flags over the defaults. With ``--resume DIR`` (or a
    checkpoint file in DIR): the checkpoint's saved config with the flags given on this command line
    over it, validated merged (so ``--total-steps 3000`` extends a run of 1000-step epochs), and
    ``output_dir`` / ``run_name`` pointing at DIR whatever the saved config says: a copied run
    continues in the copy and leaves the original alone.

    Raises:
        ValueError: an invalid merged config, or flags a resumed run cannot take (``--preset``,
            ``--overwrite``, ``--output-dir`` / ``--run-name``: it stays in its directory; ``--seed`` /
            ``--seeds`` other than its own: a run keeps its seeds).
        FileNotFoundError: no checkpoint at the ``--resume`` path.
        CheckpointError: a damaged or foreign checkpoint, or one of the retired ``LossModule`` trainer.
    """
    values = command_line_values(argv)
    resume = values.get("resume")
    if not resume:
        values.pop("preset", None)
        return TrainConfig(**values)
    if "preset" in values:
        raise ValueError(f"--preset sets up a new run; a resumed run keeps its saved config (give the flags to "
                         f"change instead: --resume {resume} --total-steps ...)")
    if values.get("overwrite"):
        raise ValueError("--resume continues a run and --overwrite starts one over; give one of them")
    from sg_torchrl.train.checkpoint import CheckpointError, resume_run_dir  # reading a checkpoint needs torch
    from sg_torchrl.train.trainer import SeedGroupTrainer

    checkpoint = SeedGroupTrainer.load_checkpoint(resume)
    refuse_retired_checkpoint(checkpoint, resume)
    saved = {name: value for name, value in checkpoint["config"].items() if name not in RETIRED_FIELDS}
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(saved) - known)
    if unknown:
        raise CheckpointError(f"the config saved in {resume} has fields this sg_torchrl does not know "
                              f"({', '.join(unknown)}): written by another version")
    for name in ("seed", "seeds"):  # a run (a group) keeps its seeds: its state holds their streams
        if name in values and values[name] != saved.get(name, [] if name == "seeds" else None):
            raise ValueError(f"a resumed run keeps its seeds ({_seeds_text(saved)}); --{name} cannot change them")
    merged = TrainConfig(**{**saved, **values, "resume": str(resume), "overwrite": False})
    run_dir = resume_run_dir(resume)
    moved = [name for name in ("output_dir", "run_name") if name in values]
    if moved and os.path.abspath(merged.run_dir) != str(run_dir):  # flags that name the run's own directory are fine
        flags = " / ".join("--" + name.replace("_", "-") for name in moved)
        raise ValueError(f"a resumed run continues in its own directory ({run_dir}); {flags} cannot move it to "
                         f"{merged.run_dir} (copy the run directory and resume the copy instead)")
    return dataclasses.replace(merged, output_dir=str(run_dir.parent), run_name=run_dir.name)


def _after_write_error(run_dir: Path) -> str:
    """What is left after a failed write, and how to go on: the last checkpoint's epoch and ``--resume``."""
    from sg_torchrl.train.checkpoint import load_checkpoint

    try:
        epoch = load_checkpoint(run_dir)["epoch"]
    except (OSError, ValueError):  # no checkpoint (the first one failed, the directory vanished), or unreadable
        return f"{run_dir} holds no checkpoint to continue from: run the same command again once the cause is fixed"
    return f"the last checkpoint (epoch {epoch}) is intact, continue with: sg-train --resume {run_dir}"


def _seeds_text(config: dict[str, Any]) -> str:
    seeds = config.get("seeds") or []
    return f"--seeds {' '.join(map(str, seeds))}" if seeds else f"--seed {config.get('seed')}"


def _print_group(cfg: TrainConfig, metrics: dict[str, Any]) -> None:
    """A seed group's end-of-run report: each seed's figures, then their mean."""
    run_dir, nan = cfg.run_dir, float("nan")
    print(f"{algorithm_title(cfg.algo)} on {cfg.env_id}, seeds {' '.join(map(str, cfg.seeds))}: "
          f"{metrics.get('Train/TotalSteps', 0):.0f} env steps per seed (cost limit {cfg.cost_limit:g})")
    for seed in cfg.seeds:
        prefix = f"seed-{seed:03d}/"
        line = (f"  seed {seed}: training EpRet {metrics.get(prefix + 'Metrics/EpRet', nan):.1f}  "
                f"EpCost {metrics.get(prefix + 'Metrics/EpCost', nan):.1f}")
        if prefix + "Metrics/EvalEpRet" in metrics:
            line += (f"   evaluation EpRet {metrics[prefix + 'Metrics/EvalEpRet']:.1f}  "
                     f"EpCost {metrics[prefix + 'Metrics/EvalEpCost']:.1f}")
        if metrics.get(prefix + "Diverged"):
            line += f"   DIVERGED in epoch {metrics[prefix + 'DivergedEpoch']}: {metrics[prefix + 'DivergedReason']}"
        print(line)
    line = f"  mean of the seeds that trained to the end: EpRet {metrics.get('Metrics/EpRet', nan):.1f}  " \
           f"EpCost {metrics.get('Metrics/EpCost', nan):.1f}"
    if "Metrics/EvalEpRet" in metrics:
        line += f"   evaluation EpRet {metrics['Metrics/EvalEpRet']:.1f}  EpCost {metrics['Metrics/EvalEpCost']:.1f}"
    print(line)
    print(f"  logs:       {run_dir}/seed-XXX/ (progress.csv, csv, summary.json, curves.png"
          + (", wandb)" if cfg.wandb != "disabled" else ")") + f", {run_dir}/summary.json")
    print(f"  checkpoint: {run_dir}/checkpoint.pt   (continue with: sg-train --resume {run_dir})")
    print(f"  plot:       {run_dir}/curves.png   (every seed's return and cost, their mean and the cost limit)")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        cfg = _resolve_resume(argv)  # a new run's config is checked whole here, before any heavy import
        check_device_available(cfg.device)  # this machine has it (a resumed run's saved device too)
        from sg_torchrl.train.checkpoint import CheckpointError, RunDirectoryError, check_new_run_dir

        if not cfg.resume:
            check_new_run_dir(cfg.run_dir, cfg.overwrite)  # before anything is built
        make_dirs(cfg.run_dir)  # an output directory that is a file, or read-only: said before anything is built
    except RunWriteError as error:
        print(f"sg-train: error: {error}", file=sys.stderr)
        return EXIT_WRITE_FAILED
    except SystemExit as stop:  # argparse: --help (0), or a bad flag (2) with its "sg-train: error:" line
        return stop.code if isinstance(stop.code, int) else 2
    except (ValueError, FileNotFoundError) as error:  # CheckpointError and RunDirectoryError included
        print(f"sg-train: error: {error}", file=sys.stderr)
        return 2
    run_dir = cfg.run_dir
    try:
        metrics = train(cfg)
    except (CheckpointError, RunDirectoryError) as error:  # the files changed since the checks above
        print(f"sg-train: error: {error}", file=sys.stderr)
        return 2
    except TrainingInterrupted as stop:
        print(f"sg-train: {stop}\n  continue with: sg-train --resume {run_dir}", file=sys.stderr)
        return stop.exit_code
    except RunWriteError as error:  # a full disk, a quota, a read-only or vanished directory
        print(f"sg-train: error: {error}; {_after_write_error(run_dir)}", file=sys.stderr)
        return EXIT_WRITE_FAILED
    print()
    if cfg.group:
        _print_group(cfg, metrics)
        return 0 if any(not metrics.get(f"seed-{seed:03d}/Diverged") for seed in cfg.seeds) else 1
    print(f"{algorithm_title(cfg.algo)} on {cfg.env_id}, seed {cfg.seed}: {metrics.get('Train/TotalSteps', 0):.0f} env steps")
    print(f"  training (last 50 episodes): EpRet {metrics.get('Metrics/EpRet', float('nan')):.1f}  "
          f"EpCost {metrics.get('Metrics/EpCost', float('nan')):.1f}  (cost limit {cfg.cost_limit:g})")
    if "Metrics/EvalEpRet" in metrics:
        print(f"  evaluation ({cfg.eval_episodes} deterministic episodes): EpRet {metrics['Metrics/EvalEpRet']:.1f}  "
              f"EpCost {metrics['Metrics/EvalEpCost']:.1f}")
    print(f"  logs:       {run_dir}/progress.csv, {run_dir}/csv" + (f", {run_dir}/wandb" if cfg.wandb != 'disabled' else ""))
    print(f"  checkpoint: {run_dir}/checkpoint.pt   (continue with: sg-train --resume {run_dir})")
    print(f"  plot:       {run_dir}/curves.png")
    if metrics.get("Diverged"):  # the engine ends a run whose parameters or update turned non-finite
        print(f"  DIVERGED in epoch {metrics['DivergedEpoch']}: {metrics['DivergedReason']}")
        return 1
    return 0
