"""A trained policy as one file that runs without sg_torchrl: ``torch.export``, observation -> mean action.

:func:`export_policy` exports the policy's network (:mod:`~sg_torchrl.evaluation.networks`: the frozen
observation normaliser, the actor's network) as its mean action with ``torch.export.export``, a dynamic
batch dimension, and saves the program with ``torch.export.save``. Reading it back needs torch alone (not
sg_torchrl, TorchRL or tensordict: the graph is ATen operators and the weights are tensors)::

    import torch
    policy = torch.export.load("policy.pt2").module()
    action = policy(obs)            # obs (B, obs_dim) float32 -> (B, action_dim), the mean action

Every family exports alike: an on-policy actor's Gaussian mean, SAC's squashed mean, TD3's and DDPG's
deterministic action, and a multi-agent team's mean actions (``(B, n_agents, obs_dim)`` -> ``(B, n_agents,
max action size)``; an agent with fewer actuators has zeros in its padding slots). A pixel run's program
takes the raw images too, in ``in_keys`` order (``pixels`` ``(B, H, W, 3)`` ``uint8``, ``depth`` ``(B, H, W,
1)``, then ``observation``). ``torch.export.load(path, extra_files={"sg_torchrl.json": ""})`` also returns a
description (``in_keys``, shapes, env id, env options, seed, epoch).

Why ``torch.export`` and not TorchScript: TorchScript (``torch.jit.script`` / ``trace``) is deprecated
in torch 2.x and no longer developed, while ``torch.export`` is the supported format (ahead-of-time
compilation, ExecuTorch and other runtimes start from it), its loader reads the weights without
unpickling arbitrary objects, and it keeps the normaliser's float64 arithmetic as it is, so the
exported actions are the library policy's (``tests/test_evaluation.py``,
``tests/test_evaluation_families.py``).
"""

from __future__ import annotations

import copy
import io
import json
import os
from pathlib import Path

import torch
from torch import Tensor, nn

from sg_torchrl.evaluation.networks import TrainedPolicy, input_dtype, key_name
from sg_torchrl.train.writes import write_atomic

__all__ = ["DESCRIPTION_FILE", "export_policy"]

#: Name of the JSON description saved with the program (``torch.export.load(..., extra_files=...)``).
DESCRIPTION_FILE = "sg_torchrl.json"


class _MeanAction(nn.Module):
    """A policy's network reduced to its mean action (what a deployed policy does)."""

    def __init__(self, network: nn.Module) -> None:
        super().__init__()
        self.network = network

    def forward(self, *inputs: Tensor) -> Tensor:
        return self.network.mean_action(*inputs)


def _example_inputs(policy: TrainedPolicy, batch: int) -> tuple[Tensor, ...]:
    return tuple(torch.zeros(batch, *policy.input_shapes[key], dtype=input_dtype(key)) for key in policy.in_keys)


def export_policy(policy: TrainedPolicy, path: str | os.PathLike) -> Path:
    """Write ``policy``'s mean action as a ``torch.export`` program to ``path`` (atomically); returns ``path``.

    The program runs on the CPU, takes the raw observation entries ``(B, ...)`` (any ``B >= 1``) in
    ``policy.in_keys`` order and returns the mean action ``(B, *policy.action_shape)`` ``float32``.

    Raises:
        RunWriteError: ``path`` could not be written.
    """
    path = Path(path)
    module = _MeanAction(copy.deepcopy(policy.network)).to("cpu").eval()  # the policy itself stays on its device
    batch = torch.export.Dim("batch")
    examples = _example_inputs(policy, batch=2)
    with torch.no_grad():
        program = torch.export.export(module, examples, dynamic_shapes={"inputs": tuple({0: batch} for _ in examples)})
    cfg = policy.config
    description = {
        "format": "torch.export program: torch.export.load(path).module()(*inputs) -> mean action "
                  "(B, *action_shape)",
        "in_keys": [key_name(key) for key in policy.in_keys],
        "input_shapes": {key_name(key): list(x.shape[1:]) for key, x in zip(policy.in_keys, examples)},
        "action_dim": int(policy.action_spec.shape[-1]),
        "action_shape": list(policy.action_shape),
        "observation_normalized_inside": policy.network.scaler is not None,
        "env_id": cfg.env_id, "env_options": cfg.env_options, "algo": cfg.algo, "seed": policy.seed,
        "epoch": policy.epoch,
    }
    buffer = io.BytesIO()
    torch.export.save(program, buffer, extra_files={DESCRIPTION_FILE: json.dumps(description)})
    return write_atomic(path, buffer.getvalue())
