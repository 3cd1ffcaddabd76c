"""Checks shared by the trainer tests (vector and pixel observations)."""

from __future__ import annotations

import torch

from sg_torchrl.train import Trainer


def flat_parameters(trainer: Trainer) -> torch.Tensor:
    """Every parameter of the actor and both critics, flattened into one vector (for exact-equality checks)."""
    modules = (trainer.actor, trainer.critic, trainer.cost_critic)
    return torch.cat([p.detach().reshape(-1) for m in modules for p in m.parameters()])
