"""Running observation normalisation, as used by SafePO's training runs.

SafePO normalises observations with gymnasium's running mean/variance (parallel Welford update,
initial count 1e-4, epsilon 1e-8, no clipping), updating the statistics with every observation
*before* normalising it. :class:`RunningObservationNorm` is that rule as a TorchRL transform whose
statistics are buffers, so checkpoints restore them; :meth:`~RunningObservationNorm.freeze` (or
:meth:`~RunningObservationNorm.frozen_copy`) stops them moving. Statistics are updated from
stepped observations (reset observations are normalised but not counted) (SafePO kept updating
during evaluation, a quirk we do not reproduce).

**Per-seed statistics.** A seed group (``sg-train --seeds``) steps the simulators of S runs in one
batched env, seed ``s``'s simulators as the ``s``-th of S equal contiguous blocks of the batch
(:func:`sg_torchrl.envs.base.block_seeds`). With ``groups=S`` the normaliser keeps one row of
statistics per block: block ``s`` of every batch updates row ``s`` only, by the same rule, and is
normalised by it, so a seed's observations are normalised exactly as its single-seed run's (the
reductions run per block, in the same order, with bit-identical results). The feature shape may have
several dims: a multi-agent group normalises ``("agents", "observation")`` with ``shape=(n_agents,
features)``, statistics per seed, agent and feature.

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

__all__ = ["RunningObservationNorm", "standardize"]


def standardize(values: torch.Tensor, mean: torch.Tensor, var: torch.Tensor, epsilon: float) -> torch.Tensor:
    """``(values - mean) / sqrt(var + epsilon)`` in float64: the normalisation every observation normaliser
    applies (the env transform, and a trained policy's folded-in copy: the same operations, the same bits)."""
    return (values.to(torch.float64) - mean) / torch.sqrt(var + epsilon)


class RunningObservationNorm(Transform):
    """Normalise ``in_keys`` by running statistics over every batch dimension (or per block of simulators).

    Args:
        shape: the trailing feature shape of the normalised entry (e.g. ``(17,)``, or ``(n_agents, 12)``
            for per-agent statistics of a multi-agent observation).
        in_keys: entries to normalise in place (default ``["observation"]``).
        epsilon: added to the variance before the square root.
        initial_count: pseudo-count of the initial (mean 0, variance 1) statistics.
        groups: ``None`` (default): one set of statistics over the whole batch. ``G``: ``G`` sets,
            one per equal contiguous block of the leading (simulator) dimension: block ``g`` of a
            batch updates and is normalised by row ``g`` of :attr:`mean`, :attr:`var` and
            :attr:`count` (shapes ``(G, *shape)``, ``(G, *shape)``, ``(G,)``).

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
        groups: int | None = None,
    ) -> None:
        super().__init__(in_keys=list(in_keys), out_keys=list(in_keys))
        if groups is not None and (isinstance(groups, bool) or not isinstance(groups, int) or groups < 1):
            raise ValueError(f"groups must be None or a positive integer, got {groups!r}")
        self.epsilon = epsilon
        self.shape = tuple(int(size) for size in shape)
        self.groups = groups
        rows = () if groups is None else (groups,)
        self.register_buffer("mean", torch.zeros(*rows, *self.shape, dtype=torch.float64))
        self.register_buffer("var", torch.ones(*rows, *self.shape, dtype=torch.float64))
        self.register_buffer("count", torch.full(rows, initial_count, dtype=torch.float64))
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
        copy = RunningObservationNorm(self.shape, in_keys=self.in_keys, epsilon=self.epsilon, groups=self.groups)
        copy.load_state_dict(self.state_dict())
        return copy.freeze()

    def group_copy(self, group: int) -> RunningObservationNorm:
        """Row ``group``'s statistics as a detached, ungrouped normaliser (a seed's own, as its single run has it)."""
        self._check_grouped()
        copy = RunningObservationNorm(self.shape, in_keys=self.in_keys, epsilon=self.epsilon)
        copy.load_state_dict(self.group_state_dict(group))
        copy.frozen = self.frozen
        return copy

    def group_state_dict(self, group: int) -> dict[str, torch.Tensor]:
        """Row ``group``'s statistics under an ungrouped normaliser's ``state_dict`` keys (copies)."""
        self._check_grouped()
        return {"mean": self.mean[group].clone(), "var": self.var[group].clone(), "count": self.count[group].clone()}

    @torch.no_grad()
    def load_group_state_dict(self, group: int, state: dict[str, torch.Tensor]) -> None:
        """Set row ``group`` from an ungrouped normaliser's ``state_dict`` (or :meth:`group_state_dict`)."""
        self._check_grouped()
        for name in ("mean", "var", "count"):
            getattr(self, name)[group].copy_(state[name])

    def _check_grouped(self) -> None:
        if self.groups is None:
            raise ValueError("this normaliser keeps one set of statistics (groups=None)")

    def _blocks(self, batch: torch.Tensor) -> torch.Tensor:
        """``batch`` (leading simulator dim first) as ``(G, -1, *shape)`` in float64: block ``g`` on row ``g``."""
        if batch.shape[0] % self.groups:
            raise ValueError(f"a batch of {batch.shape[0]} does not split into {self.groups} equal blocks")
        return batch.reshape(self.groups, -1, *self.shape).to(torch.float64)

    def _samples(self, batch: torch.Tensor) -> torch.Tensor:
        """``batch`` in float64 as ``(M, *shape)``, or with ``groups`` as ``(G, -1, *shape)`` (:meth:`_blocks`)."""
        return batch.reshape(-1, *self.shape).to(torch.float64) if self.groups is None else self._blocks(batch)

    @torch.no_grad()
    def update(self, batch: torch.Tensor) -> None:
        """Merge the moments of ``batch`` (any leading dims; per block with ``groups``) into the statistics."""
        self._merge(self._samples(batch))

    def _merge(self, flat: torch.Tensor) -> None:
        """:meth:`update` on ``batch`` already in :meth:`_samples`' float64 layout."""
        if self.groups is None:
            dim, count = 0, self.count
        else:
            dim, count = 1, self.count.view(-1, *([1] * len(self.shape)))
        batch_count = flat.shape[dim]
        batch_mean = flat.mean(dim)
        batch_var = flat.var(dim, unbiased=False)
        delta = batch_mean - self.mean
        total = count + batch_count
        self.mean += delta * batch_count / total
        m2 = self.var * count + batch_var * batch_count + delta.square() * count * batch_count / total
        self.var.copy_(m2 / total)
        self.count += batch_count

    @torch.no_grad()
    def _step(self, tensordict, next_tensordict):
        # Statistics learn from stepped observations only: on a partial reset the reset
        # TensorDict also carries the other simulators' observations, already counted here.
        # Each entry goes to float64 once, for the update and the normalisation (the same values).
        for key in self.in_keys:
            obs = next_tensordict.get(key)
            samples = self._samples(obs)
            if not self.frozen:
                self._merge(samples)
            next_tensordict.set(key, self._normalized(samples, obs))
        return next_tensordict

    def _apply_transform(self, obs: torch.Tensor) -> torch.Tensor:
        return self._normalized(self._samples(obs), obs)

    def _normalized(self, samples: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """``obs`` normalised, from its float64 :meth:`_samples`, in ``obs``'s shape and dtype."""
        mean, var = (self.mean, self.var) if self.groups is None else (self.mean.unsqueeze(1), self.var.unsqueeze(1))
        return standardize(samples, mean, var, self.epsilon).reshape(obs.shape).to(obs.dtype)

    def _reset(self, tensordict, tensordict_reset):
        return self._call(tensordict_reset)
