"""``sg-train``: typed config, the on-policy safe training loop, logging and checkpoints.

Run ``sg-train --help`` (or ``python -m sg_torchrl.train --help``) for every option.
"""

from __future__ import annotations

import sys

from sg_torchrl.train.algorithms import ALGORITHMS
from sg_torchrl.train.config import PRESETS, TrainConfig, parse_args
from sg_torchrl.train.trainer import Trainer

__all__ = ["ALGORITHMS", "PRESETS", "TrainConfig", "Trainer", "main", "train"]


def train(cfg: TrainConfig) -> dict[str, float]:
    """Run (or continue, when ``cfg.resume`` is set) one experiment; returns the final metrics."""
    checkpoint = None
    if cfg.resume:
        checkpoint = Trainer.load_checkpoint(cfg.resume)
    return Trainer(cfg, checkpoint).run()


def _resolve_resume(cfg: TrainConfig, argv: list[str]) -> TrainConfig:
    """On ``--resume``, the saved config wins except for the flags given on this command line."""
    if not cfg.resume:
        return cfg
    saved = Trainer.load_checkpoint(cfg.resume)["config"]
    given = {arg[2:].split("=")[0].replace("-", "_") for arg in argv if arg.startswith("--")}
    values = {**saved, **{k: v for k, v in cfg.to_dict().items() if k in given}, "resume": cfg.resume}
    return TrainConfig(**values)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        cfg = _resolve_resume(parse_args(argv), argv)
    except (ValueError, FileNotFoundError) as error:
        print(f"sg-train: error: {error}", file=sys.stderr)
        return 2
    metrics = train(cfg)
    run_dir = cfg.run_dir
    print()
    print(f"{ALGORITHMS[cfg.algo].title} on {cfg.env_id}, seed {cfg.seed}: {metrics.get('Train/TotalSteps', 0):.0f} env steps")
    print(f"  training (last 50 episodes): EpRet {metrics.get('Metrics/EpRet', float('nan')):.1f}  "
          f"EpCost {metrics.get('Metrics/EpCost', float('nan')):.1f}  (cost limit {cfg.cost_limit:g})")
    if "Metrics/EvalEpRet" in metrics:
        print(f"  evaluation ({cfg.eval_episodes} deterministic episodes): EpRet {metrics['Metrics/EvalEpRet']:.1f}  "
              f"EpCost {metrics['Metrics/EvalEpCost']:.1f}")
    print(f"  logs:       {run_dir}/progress.csv, {run_dir}/csv" + (f", {run_dir}/wandb" if cfg.wandb != 'disabled' else ""))
    print(f"  checkpoint: {run_dir}/checkpoint.pt   (continue with: sg-train --resume {run_dir})")
    print(f"  plot:       {run_dir}/curves.png")
    return 0
