"""Running observation normalisation, as used by SafePO's training runs.

SafePO normalises observations with gymnasium's running mean/variance (parallel Welford update,
initial count 1e-4, epsilon 1e-8, no clipping), updating the statistics with every observation
*before* normalising it. :class:`RunningObservationNorm` is that rule as a TorchRL transform whose
statistics are buffers, so checkpoints restore them; :meth:`~RunningObservationNorm.freeze` (or
:meth:`~RunningObservationNorm.frozen_copy`) stops them moving. Statistics are updated from
stepped observations (reset observations are normalised but not counted) (SafePO kept updating
during evaluation, a quirk we do not reproduce).

Freezing is a flag of its own, not ``nn.Module.training``: TorchRL puts every transform in eval
mode when it is attached to a ``TransformedEnv`` (or appended to a ``Compose``), so a
``training``-gated update would never run (TorchRL's own ``VecNorm`` has ``freeze()`` for the same
reason).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.utils import NestedKey
from torchrl.envs.transforms import Transform

__all__ = ["RunningObservationNorm"]


class RunningObservationNorm(Transform):
    """Normalise ``in_keys`` by running statistics over every batch dimension.

    Args:
        shape: the trailing feature shape of the normalised entry (e.g. ``(17,)``).
        in_keys: entries to normalise in place (default ``["observation"]``).
        epsilon: added to the variance before the square root.
        initial_count: pseudo-count of the initial (mean 0, variance 1) statistics.

    Attributes:
        frozen: when ``True``, stepping normalises without updating the statistics.
    """

    def __init__(
        self,
        shape: Sequence[int],
        in_keys: Sequence[NestedKey] = ("observation",),
        *,
        epsilon: float = 1e-8,
        initial_count: float = 1e-4,
    ) -> None:
        super().__init__(in_keys=list(in_keys), out_keys=list(in_keys))
        self.epsilon = epsilon
        self.register_buffer("mean", torch.zeros(*shape, dtype=torch.float64))
        self.register_buffer("var", torch.ones(*shape, dtype=torch.float64))
        self.register_buffer("count", torch.tensor(initial_count, dtype=torch.float64))
        self.frozen = False

    def freeze(self) -> RunningObservationNorm:
        """Stop updating the statistics (evaluation); returns ``self``."""
        self.frozen = True
        return self

    def unfreeze(self) -> RunningObservationNorm:
        """Resume updating the statistics; returns ``self``."""
        self.frozen = False
        return self

    def frozen_copy(self) -> RunningObservationNorm:
        """A frozen, detached copy with the same statistics (for an evaluation env)."""
        copy = RunningObservationNorm(self.mean.shape, in_keys=self.in_keys, epsilon=self.epsilon)
        copy.load_state_dict(self.state_dict())
        return copy.freeze()

    @torch.no_grad()
    def update(self, batch: torch.Tensor) -> None:
        """Merge the moments of ``batch`` (any leading dims) into the running statistics."""
        flat = batch.reshape(-1, *self.mean.shape).to(torch.float64)
        batch_count = flat.shape[0]
        batch_mean = flat.mean(0)
        batch_var = flat.var(0, unbiased=False)
        delta = batch_mean - self.mean
        total = self.count + batch_count
        self.mean += delta * batch_count / total
        m2 = self.var * self.count + batch_var * batch_count + delta.square() * self.count * batch_count / total
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def _step(self, tensordict, next_tensordict):
        # Statistics learn from stepped observations only: on a partial reset the reset
        # TensorDict also carries the other simulators' observations, already counted here.
        if not self.frozen:
            for key in self.in_keys:
                self.update(next_tensordict.get(key))
        return self._call(next_tensordict)

    def _apply_transform(self, obs: torch.Tensor) -> torch.Tensor:
        normalised = (obs.to(torch.float64) - self.mean) / torch.sqrt(self.var + self.epsilon)
        return normalised.to(obs.dtype)

    def _reset(self, tensordict, tensordict_reset):
        return self._call(tensordict_reset)
