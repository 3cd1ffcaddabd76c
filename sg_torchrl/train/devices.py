"""Where a run's networks and updates live: ``sg-train --device cpu|cuda|cuda:N`` (``TrainConfig.device``).

The simulators always step where their backend runs them (CPU MuJoCo, or the Warp backend's device);
``device`` places what learns: the stacked networks, the optimiser state, the multiplier values fed
to the losses, GAE, the epoch's batch and every update step, in every family (multi-agent: also the
rounds' PopArt statistics; off-policy: also the targets, while the replay buffers stay on the host and
each gradient step copies its sampled rows over once). The random streams (action noise,
minibatch order) are CPU ``torch.Generator``\\ s whatever the device, so a run draws the same numbers
on every device and its checkpoint (all CPU tensors) continues on another one.

Two checks, kept apart so that reading a saved config never depends on the machine:

* :func:`check_device_name` (no torch import): the name's form, run by ``TrainConfig.validate``;
* :func:`check_device_available`: that this machine has the device, run by ``sg-train`` with its
  option checks (exit status 2) and by every trainer before it builds anything.

:func:`training_device` is what a trainer calls: the checked :class:`torch.device` of ``cfg.device``.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

    from sg_torchrl.train.config import TrainConfig

__all__ = ["DEVICE_NAMES", "check_device_available", "check_device_name", "training_device"]

#: The forms ``--device`` takes.
DEVICE_NAMES = ("cpu", "cuda", "cuda:N")
_DEVICE = re.compile(r"cpu|cuda(:[0-9]+)?")


def check_device_name(name: object) -> None:
    """Raise ``ValueError`` unless ``name`` is ``"cpu"``, ``"cuda"`` or ``"cuda:N"``."""
    if not (isinstance(name, str) and _DEVICE.fullmatch(name)):
        raise ValueError(f"config: device must be one of {', '.join(DEVICE_NAMES)}, got {name!r}")


def check_device_available(name: str) -> None:
    """Raise ``ValueError`` naming the problem when this machine cannot train on ``name`` (a CUDA device it lacks).

    ``"cpu"`` needs nothing (and imports nothing); a CUDA name imports torch to ask it.
    """
    check_device_name(name)
    if name == "cpu":
        return
    import torch

    advice = "train on the CPU with --device cpu (a resumed run: --resume DIR --device cpu continues it there)"
    if not torch.cuda.is_available():
        built = f"torch {torch.__version__} was built without CUDA" if torch.version.cuda is None else (
            f"torch {torch.__version__} (CUDA {torch.version.cuda}) sees no CUDA device")
        raise ValueError(f"config: device {name!r} asks for CUDA, but {built}; {advice}")
    index = int(name.partition(":")[2] or 0)
    count = torch.cuda.device_count()
    if index >= count:
        raise ValueError(f"config: device {name!r} asks for CUDA device {index}, but this machine has {count} "
                         f"(cuda:0{f' to cuda:{count - 1}' if count > 1 else ''}); {advice}")


def training_device(cfg: TrainConfig) -> torch.device:
    """The :class:`torch.device` a trainer builds ``cfg``'s networks and updates on (checked: :func:`check_device_available`)."""
    import torch

    check_device_available(cfg.device)
    device = torch.device(cfg.device)
    if device.type == "cuda" and device.index is None:  # as the tensors on it name it, so devices compare equal
        device = torch.device("cuda", torch.cuda.current_device())
    return device
