"""``sg-train``: typed config, the on-policy safe training loops, logging and checkpoints.

Run ``sg-train --help`` (or ``python -m sg_torchrl.train --help``) for every option. The twelve
single-agent algorithms run in :class:`Trainer`, the four multi-agent ones (``--algo mappo``,
``happo``, ``mappo_lag``, ``macpo`` on a multi-agent env id) in :class:`MultiAgentTrainer`.
Ctrl-C (or ``SIGTERM``) stops a run after the epoch under way, checkpointed; ``--resume`` continues it.

Importing this package loads neither torch, TorchRL nor MuJoCo (seconds on a busy machine): ``main``
parses and checks the whole command line first, so a bad flag or option fails in about a second. The
trainers and the algorithm tables (:data:`_HEAVY`) are imported by their
first use (PEP 562), or by :func:`_import_trainers` once ``main`` has a valid config.
"""

from __future__ import annotations

import importlib
import sys
from typing import Any

from sg_torchrl.train.config import PRESETS, TrainConfig, parse_args
from sg_torchrl.train.interrupt import TrainingInterrupted

#: Names exported from modules that load torch: name -> its module. The functions of this module use
#: them as globals, which :func:`_import_trainers` binds.
_HEAVY = {
    "ALGORITHMS": "sg_torchrl.train.algorithms",
    "MULTI_AGENT_ALGORITHMS": "sg_torchrl.train.multi_agent",
    "MultiAgentTrainer": "sg_torchrl.train.multi_agent",
    "EpochTrainer": "sg_torchrl.train.trainer",
    "Trainer": "sg_torchrl.train.trainer",
}


def _import_trainers() -> None:
    """Import the :data:`_HEAVY` names into this module's globals (torch, TorchRL, MuJoCo: seconds)."""
    for name, module in _HEAVY.items():
        if name not in globals():
            globals()[name] = getattr(importlib.import_module(module), name)


def __getattr__(name: str) -> Any:
    if name in _HEAVY:
        _import_trainers()
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "ALGORITHMS", "MULTI_AGENT_ALGORITHMS", "PRESETS", "EpochTrainer", "MultiAgentTrainer", "TrainConfig", "Trainer",
    "TrainingInterrupted", "algorithm_title", "main", "train", "trainer_class",
]


def trainer_class(cfg: TrainConfig) -> type[EpochTrainer]:
    """:class:`MultiAgentTrainer` for the multi-agent algorithms, :class:`Trainer` for the rest."""
    _import_trainers()
    return MultiAgentTrainer if cfg.multi_agent else Trainer


def algorithm_title(algo: str) -> str:
    """Display name of an ``--algo`` value (``"mappo_lag"`` -> ``"MAPPO-Lag"``)."""
    _import_trainers()
    table = MULTI_AGENT_ALGORITHMS if algo in MULTI_AGENT_ALGORITHMS else ALGORITHMS
    return table[algo].title


def train(cfg: TrainConfig) -> dict[str, float]:
    """Run (or continue, when ``cfg.resume`` is set) one experiment; returns the final metrics."""
    cls = trainer_class(cfg)
    checkpoint = cls.load_checkpoint(cfg.resume) if cfg.resume else None
    return cls(cfg, checkpoint).run()


def _resolve_resume(cfg: TrainConfig, argv: list[str]) -> TrainConfig:
    """On ``--resume``, the saved config wins except for the flags given on this command line."""
    if not cfg.resume:
        return cfg
    saved = EpochTrainer.load_checkpoint(cfg.resume)["config"]
    given = {arg[2:].split("=")[0].replace("-", "_") for arg in argv if arg.startswith("--")}
    values = {**saved, **{k: v for k, v in cfg.to_dict().items() if k in given}, "resume": cfg.resume}
    return TrainConfig(**values)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        cfg = parse_args(argv)  # the whole command line is checked here, before any heavy import
        _import_trainers()
        cfg = _resolve_resume(cfg, argv)
    except SystemExit as stop:  # argparse: --help (0), or a bad flag (2) with its "sg-train: error:" line
        return stop.code if isinstance(stop.code, int) else 2
    except (ValueError, FileNotFoundError) as error:
        print(f"sg-train: error: {error}", file=sys.stderr)
        return 2
    run_dir = cfg.run_dir
    try:
        metrics = train(cfg)
    except TrainingInterrupted as stop:
        print(f"sg-train: {stop}\n  continue with: sg-train --resume {run_dir}", file=sys.stderr)
        return stop.exit_code
    print()
    print(f"{algorithm_title(cfg.algo)} on {cfg.env_id}, seed {cfg.seed}: {metrics.get('Train/TotalSteps', 0):.0f} env steps")
    print(f"  training (last 50 episodes): EpRet {metrics.get('Metrics/EpRet', float('nan')):.1f}  "
          f"EpCost {metrics.get('Metrics/EpCost', float('nan')):.1f}  (cost limit {cfg.cost_limit:g})")
    if "Metrics/EvalEpRet" in metrics:
        print(f"  evaluation ({cfg.eval_episodes} deterministic episodes): EpRet {metrics['Metrics/EvalEpRet']:.1f}  "
              f"EpCost {metrics['Metrics/EvalEpCost']:.1f}")
    print(f"  logs:       {run_dir}/progress.csv, {run_dir}/csv" + (f", {run_dir}/wandb" if cfg.wandb != 'disabled' else ""))
    print(f"  checkpoint: {run_dir}/checkpoint.pt   (continue with: sg-train --resume {run_dir})")
    print(f"  plot:       {run_dir}/curves.png")
    return 0
