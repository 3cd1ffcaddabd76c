"""The lean hot path of a seed group: one fused first-order minibatch step for S seeds at once.

A gradient step of SafePO's first-order loop (Safety-Gymnasium paper appendix) on its 64-sample
minibatches and [64, 64] networks is per-op overhead: the TorchRL ``LossModule`` spends most of
~1,340 aten ops on machinery (tensordict plumbing, diagnostics, dtype copies). The math of each
algorithm is not here: the loss object hands the engine its
:class:`~sg_torchrl.objectives.surrogates.SeedBatchedObjective`
(:meth:`~sg_torchrl.objectives.PPOLagLoss.seed_batched_objective`), the same surrogate its own
``forward`` evaluates, and this module runs it on seed-stacked tensors
(:class:`~sg_torchrl.modules.stacked.StackedActorCritic`) with a few dozen ops:

* :class:`FusedFirstOrderStep`: the objective's per-seed losses, backward of their **sum** over
  seeds (so seed ``s``'s gradient block is its single-seed gradient), the critics' L2 penalty
  ``critic_l2 * sum(p ** 2)`` added to the gradient in closed form (``2 * critic_l2 * p``, one op
  on the flat buffer instead of ~40 in the graph), then :class:`SeedMaskedAdam`;
* :class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam`: Adam with per-seed
  step counts, per-seed gradient clip and an ``active`` mask that freezes a seed whose KL early
  stop fired while the others go on;
* :func:`batch_kl` (each seed's KL(old || new) over its whole batch, the early-stop statistic),
  :class:`SeedBatch` (a seed group's per-sample fields packed in one tensor, so a minibatch is one
  gather) and :class:`SeedShuffler` (one ``torch.Generator`` per seed for the minibatch order,
  seeded as the single-seed trainer seeds its own).

Nothing here calls ``.item()``; diagnostics come from the objective's
:meth:`~sg_torchrl.objectives.surrogates.SeedBatchedObjective.diagnostics`, for logging steps only.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor

from sg_torchrl import seeding
from sg_torchrl.modules.stacked import StackedActorCritic, quiet_layout_warning
from sg_torchrl.objectives.kl import gaussian_kl
from sg_torchrl.objectives.surrogates import SeedBatchedObjective
from sg_torchrl.train.compiling import CompileFallback
from sg_torchrl.train.seed_adam import SeedMaskedAdam

__all__ = [
    "FusedFirstOrderStep", "SeedBatch", "SeedShuffler", "batch_kl", "multiplier_values", "objective_of",
]


def objective_of(loss, *, critics_only: bool = False) -> SeedBatchedObjective:
    """The seed-batched form of ``loss``, from the loss object itself (the engine's only way to get one).

    Raises:
        TypeError: if the loss has no ``seed_batched_objective()`` (e.g. a plain TorchRL loss or
            one written without its seed-batched form): the engine never trains it as another
            algorithm.
    """
    method = getattr(loss, "seed_batched_objective", None)
    if method is None:
        raise TypeError(
            f"{type(loss).__name__} has no seed_batched_objective(): the engine trains a loss only in the "
            f"seed-batched form the loss defines (subclass PPOLagLoss with your own Surrogate; see the README's "
            f"'Add an algorithm')"
        )
    objective = method(critics_only=critics_only)
    if not isinstance(objective, SeedBatchedObjective):
        raise TypeError(f"{type(loss).__name__}.seed_batched_objective() returned {type(objective).__name__}, "
                        f"not a SeedBatchedObjective")
    return objective


def multiplier_values(multipliers: Sequence, dtype: torch.dtype = torch.float32) -> Tensor:
    """Each seed's multiplier value, ``(S,)`` in ``dtype`` (cast per seed, as ``combine`` casts it)."""
    return torch.stack([m.value.to(dtype) for m in multipliers])


# ---------------------------------------------------------------------------- batches
class SeedBatch:
    """Per-sample fields of S seeds' batches, packed in one ``(S, N, F)`` tensor (images kept apart).

    A minibatch of every field is one advanced-indexing gather (:meth:`gather`) instead of one per
    field, and :meth:`fields` splits it back into views with one ``torch.split``. Every field is
    kept with a trailing feature dimension: scalars per sample (advantages, targets, log-probs) are
    ``(S, N, 1)``, which is also the shape the losses compute in. Like a TensorDict for
    :func:`~sg_torchrl.objectives.passes.run_passes`: ``len(batch)`` is the samples per seed and
    ``batch[index]`` a minibatch.

    **Images.** A field given as a TensorDict of batch ``[S, N]`` (an image observation,
    :meth:`~sg_torchrl.modules.stacked.StackedActorCritic.read_observation`) is split: its flat vector
    (entry ``"observation"``, if any) is packed with the other fields under the field's name, and its
    other entries (``uint8`` pixels, depth) stay in their own dtype and shape in :attr:`apart`,
    gathered with the same index; :meth:`fields` hands the field back as a TensorDict. So a minibatch
    of images is one ``index_select`` per image entry and an epoch's images are never copied to float.
    """

    def __init__(self, data: Tensor, names: Sequence[str], widths: Sequence[int], *,
                 apart: Mapping[str, TensorDictBase] | None = None) -> None:
        self.data = data
        self.names = tuple(names)
        self.widths = tuple(int(w) for w in widths)
        #: Field name -> the entries of a TensorDict field kept beside :attr:`data` (batch ``[S, N]``).
        self.apart = dict(apart or {})
        # where each seed's rows start in data viewed as (S * N, F)
        self._offsets = torch.arange(data.shape[0], device=data.device).unsqueeze(1) * data.shape[1]

    @classmethod
    def pack(cls, fields: Mapping[str, Tensor | TensorDictBase]) -> SeedBatch:
        """Pack ``(S, N)`` or ``(S, N, k)`` tensors (one dtype) into one batch; TensorDict fields are split
        (see the class docstring)."""
        if not fields:
            raise ValueError("SeedBatch.pack needs at least one field")
        tensors, apart = {}, {}
        for name, value in fields.items():
            if isinstance(value, TensorDictBase):
                apart[name] = value.exclude("observation")
                if "observation" in value.keys():
                    tensors[name] = value.get("observation")
            else:
                tensors[name] = value
        columns = [value if value.dim() == 3 else value.unsqueeze(-1) for value in tensors.values()]
        shapes = {tuple(column.shape[:2]) for column in columns} | {tuple(td.batch_size) for td in apart.values()}
        if len(shapes) != 1:
            raise ValueError(f"fields differ in (seeds, samples): {sorted(shapes)}")
        return cls(torch.cat(columns, dim=-1), list(tensors), [column.shape[-1] for column in columns], apart=apart)

    @property
    def field_names(self) -> tuple[str, ...]:
        """Every field's name: the packed ones, then those with entries apart (not packed)."""
        return self.names + tuple(name for name in self.apart if name not in self.names)

    @property
    def num_seeds(self) -> int:
        return self.data.shape[0]

    def fields(self) -> dict[str, Tensor | TensorDictBase]:
        """Every field as a view ``(S, N, width)``, a field with entries apart as a TensorDict."""
        return field_views(self.data, self.names, self.widths, self.apart)

    def __len__(self) -> int:
        """The samples per seed: what minibatch indices range over (``len(data)`` in ``run_passes``)."""
        return self.data.shape[1]

    def __getitem__(self, key: str | Tensor) -> Tensor | SeedBatch:
        """A field by name (a view ``(S, N, width)``) or, as a TensorDict, the minibatch ``key`` (:meth:`gather`)."""
        if isinstance(key, str):
            return self.fields()[key]
        return self.gather(key)

    def gather(self, index: Tensor) -> SeedBatch:
        """The minibatch ``index`` (``(S, mb)``: seed ``s`` takes its samples ``index[s]``)."""
        rows = (index + self._offsets).view(-1)  # index_select on the flat rows: faster than advanced indexing
        gathered = self.data.reshape(-1, self.data.shape[-1]).index_select(0, rows)

        def pick(value: Tensor) -> Tensor:
            trailing = value.shape[2:]
            return value.reshape(-1, *trailing).index_select(0, rows).view(*index.shape, *trailing)

        apart = {name: td.apply(pick, batch_size=index.shape) for name, td in self.apart.items()}
        return SeedBatch(gathered.view(*index.shape, -1), self.names, self.widths, apart=apart)


def field_views(data: Tensor, names: Sequence[str], widths: Sequence[int],
                apart: Mapping[str, TensorDictBase]) -> dict[str, Tensor | TensorDictBase]:
    """:meth:`SeedBatch.fields` of a packed tensor and its entries apart: the packed views, and each field with
    entries apart as a TensorDict of those and (under ``"observation"``) its packed vector."""
    views: dict[str, Tensor | TensorDictBase] = dict(zip(names, torch.split(data, widths, dim=-1)))
    for name, entries in apart.items():
        td = entries.copy()
        if name in views:
            td.set("observation", views[name])
        views[name] = td
    return views


class SeedShuffler:
    """The minibatch order of each seed, from one ``torch.Generator`` per seed.

    ``SeedShuffler(seeds)`` seeds generator ``s`` with ``seeds[s]`` as the single-seed trainer seeds
    its ``minibatch_rng``, and :meth:`permutation` draws ``torch.randperm(n, generator=g_s)`` per seed,
    so seed ``s`` visits its samples in the same order as its single-seed run, whatever S is.

    With an ``active`` mask only the active seeds draw: a seed whose KL early stop fired takes no
    further pass of its single-seed run, so its generator must not advance either (its rows get
    ``arange(n)``, which its masked step ignores), or its next epoch's order would differ.
    """

    def __init__(self, seeds: Sequence[int]) -> None:
        self.generators = [seeding.generator(int(s), seeding.Purpose.MINIBATCHES) for s in seeds]
        if not self.generators:
            raise ValueError("SeedShuffler needs seeds")

    @classmethod
    def from_generators(cls, generators: Sequence[torch.Generator]) -> SeedShuffler:
        """A shuffler over generators the caller already holds (one per seed, in seed order)."""
        shuffler = cls.__new__(cls)
        shuffler.generators = list(generators)
        if not shuffler.generators:
            raise ValueError("SeedShuffler needs generators")
        return shuffler

    def permutation(self, n: int, active: Sequence[bool] | None = None) -> Tensor:
        """One permutation of ``range(n)`` per seed, ``(S, n)``; an inactive seed draws none (``arange(n)``)."""
        if active is None:
            return torch.stack([torch.randperm(n, generator=g) for g in self.generators])
        return torch.stack([torch.randperm(n, generator=g) if on else torch.arange(n)
                            for g, on in zip(self.generators, active, strict=True)])

    def minibatches(self, n: int, size: int, active: Sequence[bool] | None = None, *,
                    device: torch.device | str | None = None) -> Iterator[Tensor]:
        """A shuffled pass: ``(S, size)`` index blocks (the last one shorter when ``size`` does not divide ``n``).

        ``active``: which seeds draw their order (:meth:`permutation`); ``None``: all. ``device``: where
        the blocks are used (the batch's); the pass's order is drawn on the CPU and copied there once.
        """
        order = self.permutation(n, active)
        if device is not None:
            order = order.to(device, non_blocking=True)
        for start in range(0, n, size):
            yield order[:, start : start + size]

    def state_dict(self) -> dict[str, list[Tensor]]:
        return {"generators": [g.get_state() for g in self.generators]}

    def load_state_dict(self, state: Mapping[str, list[Tensor]]) -> None:
        for generator, value in zip(self.generators, state["generators"], strict=True):
            generator.set_state(value)


@torch.no_grad()
def batch_kl(model: StackedActorCritic, obs: Tensor, old_loc: Tensor, old_scale: Tensor,
             chunk_size: int | None = None) -> Tensor:
    """Each seed's mean KL(old || current policy) over its batch, ``(S,)``: SafePO's early-stop statistic.

    ``obs`` ``(S, N, obs_dim)``; ``old_loc`` / ``old_scale`` the rollout (or stage-one) policy's
    parameters at those observations. ``chunk_size`` samples per forward pass (``None``: all).
    """
    size = obs.shape[1]
    step = size if chunk_size is None else max(int(chunk_size), 1)
    if step >= size:  # one pass: the mean, as the single-seed trainer takes it
        loc, scale = model.dist_params(obs)
        return gaussian_kl(old_loc, old_scale, loc, scale).mean(-1)
    total = None
    for start in range(0, size, step):
        part = slice(start, start + step)
        loc, scale = model.dist_params(obs[:, part])
        kl = gaussian_kl(old_loc[:, part], old_scale[:, part], loc, scale).sum(-1)
        total = kl if total is None else total + kl
    return total / size


# ---------------------------------------------------------------------------- the step
class FusedFirstOrderStep:
    """One minibatch gradient step of SafePO's first-order loop for every seed of a group.

    ``step(batch, lam, active)``: the losses of the objective (:meth:`SeedBatchedObjective.losses`) on the
    packed minibatch ``batch`` (``(S, mb, F)``), backward of their sum over seeds and terms, the
    critics' L2 gradient ``2 * critic_l2 * p`` added on the flat buffer, then ``optimizer.step``
    (per-seed clip and masked Adam) on the optimiser groups of ``spec.groups``: the actor unless the
    objective is ``"critics"``, the critics unless it is actor-only. Seed ``s``'s gradient and update
    are those of its single-seed trainer step (``PPOLagLoss`` & co., ``clip_grad_norm_`` over the
    parameters stepped, ``torch.optim.Adam``) to float rounding.

    Args:
        model: the seed group's networks.
        optimizer: a :class:`SeedMaskedAdam` whose group 0 is ``model.flat_actor`` and group 1
            ``model.flat_critics`` (:meth:`make_optimizer` builds it).
        spec: what to compute: the loss's :class:`SeedBatchedObjective` (:func:`objective_of`).
        compile: run the losses (forward and their backward) through ``torch.compile``; when that
            fails (e.g. no C++ compiler) the step warns once, records ``compilation.compile_error`` and runs
            eagerly.
    """

    def __init__(self, model: StackedActorCritic, optimizer: SeedMaskedAdam, spec: SeedBatchedObjective, *,
                 compile: bool = False) -> None:
        groups, flat = optimizer.param_groups, model.flat_groups
        if any(len(groups) <= i or len(groups[i]["params"]) != 1 or groups[i]["params"][0] is not flat[i]
               for i in spec.groups):
            raise ValueError("the optimiser's groups must be [model.flat_actor] and [model.flat_critics] "
                             "(see FusedFirstOrderStep.make_optimizer)")
        self.model = model
        self.optimizer = optimizer
        self.spec = spec
        self.groups = spec.groups
        #: The losses, compiled or eager (its ``compiled`` and ``compile_error`` say which, and why).
        self.compilation = CompileFallback(self._eager_losses, owner="FusedFirstOrderStep", compile=compile)
        self._backward_seen = False

    @staticmethod
    def make_optimizer(model: StackedActorCritic, actor_lr: float, critic_lr: float, *,
                       max_grad_norm: float | None = 40.0, compile: bool = False, **adam) -> SeedMaskedAdam:
        """The trainer's optimiser for ``model``: actor group, critics group, per-seed clip at ``max_grad_norm``."""
        return SeedMaskedAdam([{"params": [model.flat_actor], "lr": actor_lr},
                               {"params": [model.flat_critics], "lr": critic_lr}],
                              max_grad_norm=max_grad_norm, compile=compile, **adam)

    def _eager_losses(self, data: Tensor, lam: Tensor, names: tuple[str, ...], widths: tuple[int, ...],
                      apart: Mapping[str, TensorDictBase]) -> tuple[Tensor, ...]:
        return self.spec.losses(self.model, field_views(data, names, widths, apart), lam)

    def backward(self, batch: SeedBatch, lam: Tensor) -> tuple[Tensor, ...]:
        """Gradients of the minibatch losses into the flat gradient buffers (zeroed first).

        Returns the per-seed losses, detached: ``(objective,)`` for an actor-only objective,
        ``(reward critic MSE, cost critic MSE)`` for ``"critics"``, else ``(objective, reward critic
        MSE, cost critic MSE)`` (the critics' without the L2 term, see :meth:`SeedBatchedObjective.diagnostics`).
        """
        missing = set(self.spec.fields) - set(batch.field_names)
        if missing:
            raise KeyError(f"the batch lacks {sorted(missing)} (fields: {batch.field_names})")
        model = self.model
        for index in self.groups:
            model.flat_groups[index].grad.zero_()
        losses = self.compilation(batch.data, lam, batch.names, batch.widths, batch.apart)
        total = losses[0]
        for loss in losses[1:]:
            total = total + loss
        if self._backward_seen:
            total.sum().backward()
        else:
            with quiet_layout_warning():
                total.sum().backward()
            self._backward_seen = True
        if not self.spec.actor_only and self.spec.critic_l2:
            model.flat_critics.grad.add_(model.flat_critics, alpha=2 * self.spec.critic_l2)
        return tuple(loss.detach() for loss in losses)

    def update(self, active: Tensor | None = None) -> Tensor | None:
        """The optimiser step on this objective's groups; returns each seed's gradient norm (or ``None``)."""
        return self.optimizer.step(active, groups=self.groups)

    def __call__(self, batch: SeedBatch, lam: Tensor, active: Tensor | None = None) -> tuple[Tensor, ...]:
        """:meth:`backward` then :meth:`update`; returns the detached per-seed losses."""
        losses = self.backward(batch, lam)
        self.update(active)
        return losses
