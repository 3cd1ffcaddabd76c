"""The lean hot path of a seed group: one fused first-order minibatch step for S seeds at once.

A gradient step of SafePO's first-order loop (Safety-Gymnasium paper appendix; ``minibatch_passes``
in :mod:`sg_torchrl.train.updates`) on its 64-sample minibatches and [64, 64] networks is per-op
overhead: the TorchRL ``LossModule`` spends most of ~1,340 aten ops on machinery (tensordict
plumbing, diagnostics, dtype copies). This module computes the same losses with a few dozen ops on
seed-stacked tensors (:class:`~sg_torchrl.train.stacked.StackedActorCritic`) and steps S seeds
together:

* :func:`policy_loss` / :func:`critic_losses`: PPO-clip on ``multiplier.combine``'s advantage
  (PPO, PPO-Lag, CPPO-PID: :class:`~sg_torchrl.objectives.PPOLagLoss`), the importance-weighted PG
  (:class:`~sg_torchrl.objectives.PGLoss`), FOCOPS and CUP's projection stage, and the critics'
  MSE, per seed: the mean over the seed's minibatch, ``(S,)``; the objective ``"critics"`` is the
  critics' MSE alone, the minibatch passes of the second-order algorithms (whose actor moves by the
  trust-region step of :mod:`sg_torchrl.train.stacked_trust_region` instead);
* :class:`FusedFirstOrderStep`: backward of the **sum** over seeds (so seed ``s``'s gradient block
  is its single-seed gradient), the critics' L2 penalty ``critic_l2 * sum(p ** 2)`` added to the
  gradient in closed form (``2 * critic_l2 * p``, one op on the flat buffer instead of ~40 in the
  graph), then :class:`SeedMaskedAdam`;
* :class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam` (re-exported here): Adam with per-seed
  step counts, per-seed gradient clip and an ``active`` mask that freezes a seed whose KL early
  stop fired while the others go on;
* :func:`batch_kl` (each seed's KL(old || new) over its whole batch, the early-stop statistic),
  :class:`SeedBatch` (a seed group's per-sample fields packed in one tensor, so a minibatch is one
  gather) and :class:`SeedShuffler` (one ``torch.Generator`` per seed for the minibatch order,
  seeded as the single-seed trainer seeds its own).

Nothing here calls ``.item()``; diagnostics (clip fraction, ratios, losses with the L2 term) come
from :func:`first_order_diagnostics`, for logging steps only.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

from sg_torchrl import seeding
from sg_torchrl.objectives.kl import gaussian_kl
from sg_torchrl.train.seed_adam import SeedMaskedAdam, clip_grad_norm_per_seed_
from sg_torchrl.train.stacked import StackedActorCritic, gaussian_log_prob, quiet_layout_warning

__all__ = [
    "FirstOrderSpec", "FusedFirstOrderStep", "SeedBatch", "SeedMaskedAdam", "SeedShuffler", "batch_kl",
    "clip_grad_norm_per_seed_", "combine_advantages", "combine_rule", "critic_losses", "first_order_diagnostics",
    "multiplier_values", "policy_loss",
]

Objective = Literal["ppo", "pg", "focops", "cup_projection", "critics"]
CombineRule = Literal["sum_norm", "diff_norm", "plain"]


# ---------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class FirstOrderSpec:
    """What a fused first-order step computes (one algorithm for every seed of the group).

    Attributes:
        objective: ``"ppo"`` (clipped surrogate: PPO, PPO-Lag, CPPO-PID, CUP's stage one), ``"pg"``
            (plain importance weighting), ``"focops"``, ``"cup_projection"`` (CUP's stage two,
            actor only) or ``"critics"`` (the critics alone: the second-order algorithms' passes, as
            ``PPOLagLoss.critic_losses``; no KL early stop, the actor does not move).
        combine: how the multiplier combines the advantages (:func:`combine_rule`).
        clip_epsilon: PPO's ratio clip.
        critic_l2: weight of ``sum(p ** 2)`` over each critic's parameters (0: none).
        temperature, kl_threshold, safepo_broadcast: FOCOPS's :math:`\\lambda_F`, its per-sample
            trust region :math:`\\delta` and SafePO's broadcasting quirk (see ``FOCOPSLoss``).
        cup_cost_coeff: CUP's :math:`c = (1 - \\gamma\\lambda) / (1 - \\gamma)`.
    """

    objective: Objective = "ppo"
    combine: CombineRule = "sum_norm"
    clip_epsilon: float = 0.2
    critic_l2: float = 1e-3
    temperature: float = 1.5
    kl_threshold: float = 0.02
    safepo_broadcast: bool = False
    cup_cost_coeff: float = 5.95
    _clip_bounds: tuple[float, float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.objective not in ("ppo", "pg", "focops", "cup_projection", "critics"):
            raise ValueError(f"unknown objective {self.objective!r}")
        if self.combine not in ("sum_norm", "diff_norm", "plain"):
            raise ValueError(f"unknown combine rule {self.combine!r}")
        # The single-seed loss takes log1p of its float32 clip buffer; the same float32 values here.
        eps = torch.tensor(self.clip_epsilon, dtype=torch.float32)
        object.__setattr__(self, "_clip_bounds", ((-eps).log1p().item(), eps.log1p().item()))

    @property
    def actor_only(self) -> bool:
        """Whether only the actor learns (CUP's projection)."""
        return self.objective == "cup_projection"

    @property
    def critics_only(self) -> bool:
        """Whether only the critics learn (the second-order algorithms' minibatch passes)."""
        return self.objective == "critics"

    @property
    def groups(self) -> tuple[int, ...]:
        """The optimiser groups the step moves: 0 the actor, 1 the critics (``FusedFirstOrderStep.make_optimizer``)."""
        if self.actor_only:
            return (0,)
        return (1,) if self.critics_only else (0, 1)

    @property
    def num_losses(self) -> int:
        """How many per-seed losses a step returns: the objective (unless critics only), then each critic's."""
        return (0 if self.critics_only else 1) + (0 if self.actor_only else 2)

    @property
    def kl_stop(self) -> bool:
        """Whether the passes stop on the policy's KL (SafePO's early stop); not when only the critics move."""
        return not self.critics_only

    @property
    def fields(self) -> tuple[str, ...]:
        """The :class:`SeedBatch` fields the step reads."""
        if self.critics_only:
            return ("observation", "value_target", "cost_value_target")
        if self.objective == "cup_projection":
            return ("observation", "action", "action_log_prob", "cost_advantage", "stage1_loc", "stage1_scale")
        names = ("observation", "action", "action_log_prob", "advantage", "cost_advantage", "value_target",
                 "cost_value_target")
        return names + (("loc", "scale") if self.objective == "focops" else ())

    @classmethod
    def from_loss(cls, loss, *, critics_only: bool = False) -> FirstOrderSpec:
        """The spec of a single-seed first-order loss (``PPOLagLoss``, ``PGLoss``, ``FOCOPSLoss``, ``CUPLoss``).

        ``CUPLoss`` gives its projection stage; its ``reward_stage`` gives stage one. With
        ``critics_only``, the ``"critics"`` spec of the loss's ``critic_losses`` (what the single-seed
        second-order update trains its critics with), the same checks applying. Raises
        ``ValueError`` for options the fused step does not implement (entropy bonus, value clipping,
        in-loss advantage normalisation, non-MSE critics, critic coefficients other than 1).
        """
        from sg_torchrl.objectives import CUPLoss, FOCOPSLoss, PGLoss

        unsupported = {
            "entropy_bonus": bool(loss.entropy_bonus),
            "clip_value": loss.clip_value is not None,
            "normalize_advantage": bool(loss.normalize_advantage),
            "loss_critic_type != 'l2'": loss.loss_critic_type != "l2",
            "critic_coeff != 1": loss.critic_coeff is not None and float(loss.critic_coeff) != 1.0,
            "cost_critic_coeff != 1": float(loss.cost_critic_coeff) != 1.0,
            "delay_actor / max_importance_ratio": bool(loss.delay_actor) or loss.max_importance_ratio is not None,
        }
        used = [name for name, present in unsupported.items() if present]
        if used:
            raise ValueError(f"the fused step does not implement: {', '.join(used)}")
        l2 = 0.0 if loss.critic_l2_coeff is None else float(loss.critic_l2_coeff)
        common = dict(combine=combine_rule(loss.multiplier), critic_l2=l2, clip_epsilon=float(loss.clip_epsilon))
        if critics_only:
            return cls("critics", **common)
        if isinstance(loss, CUPLoss):
            return cls("cup_projection", cup_cost_coeff=float(loss.cost_coeff), **common)
        if isinstance(loss, FOCOPSLoss):
            return cls("focops", temperature=float(loss.temperature), kl_threshold=float(loss.target_kl),
                       safepo_broadcast=loss.safepo_broadcast, **common)
        if isinstance(loss, PGLoss):
            return cls("pg", **common)
        return cls("ppo", **common)


def combine_rule(multiplier) -> CombineRule:
    """The advantage rule of a :class:`~sg_torchrl.objectives.Multiplier` (``diff_norm`` > ``sum_norm`` > plain)."""
    if multiplier.diff_norm:
        return "diff_norm"
    return "sum_norm" if multiplier.sum_norm else "plain"


def multiplier_values(multipliers: Sequence, dtype: torch.dtype = torch.float32) -> Tensor:
    """Each seed's multiplier value, ``(S,)`` in ``dtype`` (cast per seed, as ``combine`` casts it)."""
    return torch.stack([m.value.to(dtype) for m in multipliers])


def combine_advantages(advantage: Tensor, cost_advantage: Tensor, lam: Tensor, rule: CombineRule) -> Tensor:
    """``Multiplier.combine`` with a per-seed :math:`\\lambda` (``(S,)``) on ``(S, N, ...)`` advantages."""
    lam = lam.to(advantage.dtype).view(-1, *([1] * (advantage.dim() - 1)))
    if rule == "diff_norm":
        return (1 - lam) * advantage - lam * cost_advantage
    if rule == "sum_norm":
        return (advantage - lam * cost_advantage) / (1 + lam)
    return advantage - lam * cost_advantage


# ---------------------------------------------------------------------------- batches
class SeedBatch:
    """Per-sample fields of S seeds' batches, packed in one ``(S, N, F)`` tensor.

    A minibatch of every field is one advanced-indexing gather (:meth:`gather`) instead of one per
    field, and :meth:`fields` splits it back into views with one ``torch.split``. Every field is
    kept with a trailing feature dimension: scalars per sample (advantages, targets, log-probs) are
    ``(S, N, 1)``, which is also the shape the losses compute in. Like a TensorDict for
    :func:`~sg_torchrl.objectives.passes.run_passes`: ``len(batch)`` is the samples per seed and
    ``batch[index]`` a minibatch.
    """

    def __init__(self, data: Tensor, names: Sequence[str], widths: Sequence[int], *,
                 _offsets: Tensor | None = None) -> None:
        self.data = data
        self.names = tuple(names)
        self.widths = tuple(int(w) for w in widths)
        if _offsets is None:  # where each seed's rows start in data viewed as (S * N, F)
            _offsets = torch.arange(data.shape[0], device=data.device).unsqueeze(1) * data.shape[1]
        self._offsets = _offsets

    @classmethod
    def pack(cls, fields: Mapping[str, Tensor]) -> SeedBatch:
        """Pack ``(S, N)`` or ``(S, N, k)`` tensors (one dtype) into one batch."""
        if not fields:
            raise ValueError("SeedBatch.pack needs at least one field")
        columns = [value if value.dim() == 3 else value.unsqueeze(-1) for value in fields.values()]
        shapes = {tuple(column.shape[:2]) for column in columns}
        if len(shapes) != 1:
            raise ValueError(f"fields differ in (seeds, samples): {sorted(shapes)}")
        return cls(torch.cat(columns, dim=-1), list(fields), [column.shape[-1] for column in columns])

    @property
    def num_seeds(self) -> int:
        return self.data.shape[0]

    @property
    def num_samples(self) -> int:
        return self.data.shape[1]

    def fields(self) -> dict[str, Tensor]:
        """Every field as a view ``(S, N, width)``."""
        return dict(zip(self.names, torch.split(self.data, self.widths, dim=-1)))

    def __len__(self) -> int:
        """The samples per seed: what minibatch indices range over (``len(data)`` in ``run_passes``)."""
        return self.num_samples

    def __getitem__(self, key: str | Tensor) -> Tensor | SeedBatch:
        """A field by name (a view ``(S, N, width)``) or, as a TensorDict, the minibatch ``key`` (:meth:`gather`)."""
        if isinstance(key, str):
            return self.fields()[key]
        return self.gather(key)

    def gather(self, index: Tensor) -> SeedBatch:
        """The minibatch ``index`` (``(S, mb)``: seed ``s`` takes its samples ``index[s]``)."""
        rows = (index + self._offsets).view(-1)  # index_select on the flat rows: faster than advanced indexing
        gathered = self.data.reshape(-1, self.data.shape[-1]).index_select(0, rows)
        return SeedBatch(gathered.view(*index.shape, -1), self.names, self.widths)


class SeedShuffler:
    """The minibatch order of each seed, from one ``torch.Generator`` per seed.

    ``SeedShuffler(seeds)`` seeds generator ``s`` with ``seeds[s]`` as the single-seed trainer seeds
    its ``minibatch_rng``, and :meth:`permutation` draws ``torch.randperm(n, generator=g_s)`` per seed,
    so seed ``s`` visits its samples in the same order as its single-seed run, whatever S is.

    With an ``active`` mask only the active seeds draw: a seed whose KL early stop fired takes no
    further pass of its single-seed run, so its generator must not advance either (its rows get
    ``arange(n)``, which its masked step ignores), or its next epoch's order would differ.
    """

    def __init__(self, seeds: Sequence[int] = (), *, generators: Sequence[torch.Generator] | None = None) -> None:
        self.generators = list(generators) if generators is not None else [
            seeding.generator(int(s), seeding.Purpose.MINIBATCHES) for s in seeds]
        if not self.generators:
            raise ValueError("SeedShuffler needs seeds or generators")

    def permutation(self, n: int, active: Sequence[bool] | None = None) -> Tensor:
        """One permutation of ``range(n)`` per seed, ``(S, n)``; an inactive seed draws none (``arange(n)``)."""
        if active is None:
            return torch.stack([torch.randperm(n, generator=g) for g in self.generators])
        return torch.stack([torch.randperm(n, generator=g) if on else torch.arange(n)
                            for g, on in zip(self.generators, active, strict=True)])

    def minibatches(self, n: int, size: int, active: Sequence[bool] | None = None) -> Iterator[Tensor]:
        """A shuffled pass: ``(S, size)`` index blocks (the last one shorter when ``size`` does not divide ``n``).

        ``active``: which seeds draw their order (:meth:`permutation`); ``None``: all.
        """
        order = self.permutation(n, active)
        for start in range(0, n, size):
            yield order[:, start : start + size]

    def state_dict(self) -> dict[str, list[Tensor]]:
        return {"generators": [g.get_state() for g in self.generators]}

    def load_state_dict(self, state: Mapping[str, list[Tensor]]) -> None:
        for generator, value in zip(self.generators, state["generators"], strict=True):
            generator.set_state(value)


# ---------------------------------------------------------------------------- losses
def policy_loss(model: StackedActorCritic, batch: Mapping[str, Tensor], lam: Tensor, spec: FirstOrderSpec) -> Tensor:
    """Each seed's policy loss on its minibatch, ``(S,)`` (differentiable in the actor).

    ``batch`` holds :meth:`SeedBatch.fields` views (``(S, mb, width)``); ``lam`` is each seed's
    multiplier value ``(S,)`` (:func:`multiplier_values`; CUP's :math:`\\nu`). Per sample, with
    :math:`r` the ratio to the rollout policy and :math:`A` the combined advantage:

    * ``ppo``: :math:`-\\min(rA, \\mathrm{clip}(r, 1 \\pm \\epsilon) A)`;
    * ``pg``: :math:`-rA`;
    * ``focops``: :math:`(\\mathrm{KL}_i - rA/\\lambda_F)\\,\\mathbb 1\\{\\mathrm{KL}_i \\le \\delta\\}`,
      :math:`\\mathrm{KL}_i` from the current policy to the stored ``loc`` / ``scale``;
    * ``cup_projection``: :math:`\\nu c\\, r A_c + \\mathrm{KL}(\\pi_\\theta \\| \\pi_{\\text{stage1}})`.
    """
    loc, scale = model.dist_params(batch["observation"])
    log_ratio = gaussian_log_prob(batch["action"], loc, scale).unsqueeze(-1) - batch["action_log_prob"]
    if spec.objective == "cup_projection":
        kl = gaussian_kl(loc, scale, batch["stage1_loc"], batch["stage1_scale"]).unsqueeze(-1)
        nu_c = lam.to(loc.dtype).view(-1, 1, 1) * spec.cup_cost_coeff
        return (nu_c * log_ratio.exp() * batch["cost_advantage"] + kl).mean((1, 2))
    advantage = combine_advantages(batch["advantage"], batch["cost_advantage"], lam, spec.combine)
    if spec.objective == "ppo":
        clipped = log_ratio.clamp(*spec._clip_bounds)
        loss = -torch.minimum(log_ratio.exp() * advantage, clipped.exp() * advantage)
    elif spec.objective == "pg":
        loss = -log_ratio.exp() * advantage
    else:  # focops
        kl = gaussian_kl(loc, scale, batch["loc"], batch["scale"]).unsqueeze(-1)
        inside = (kl.detach() <= spec.kl_threshold).to(kl.dtype)
        weighted_gain = log_ratio.exp() * advantage / spec.temperature
        if spec.safepo_broadcast:
            loss = kl * inside - inside.mean(1, keepdim=True) * weighted_gain
        else:
            loss = (kl - weighted_gain) * inside
    return loss.mean((1, 2))


def critic_losses(model: StackedActorCritic, batch: Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
    """Each seed's reward- and cost-critic MSE to the targets, ``(S,)`` each, **without** the L2 term.

    :class:`FusedFirstOrderStep` adds the L2 term's gradient in closed form;
    :func:`first_order_diagnostics` adds its value.
    """
    obs = batch["observation"]
    value = model.critic(obs)
    cost_value = model.cost_critic(obs)
    return ((value - batch["value_target"]) ** 2).mean((1, 2)), ((cost_value - batch["cost_value_target"]) ** 2).mean((1, 2))


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


@torch.no_grad()
def first_order_diagnostics(model: StackedActorCritic, batch: SeedBatch, lam: Tensor, spec: FirstOrderSpec,
                            ) -> dict[str, Tensor]:
    """Per-seed ``(S,)`` diagnostics of one minibatch, for logging steps (not in the hot path).

    ``loss_objective``, ``loss_critic`` and ``loss_cost_critic`` (the critics' with their L2 term,
    as ``PPOLagLoss`` reports them), ``kl_approx`` (mean log old / new), ``mean_ratio``, ``max_ratio``
    and, per objective, ``clip_fraction`` (PPO), ``kl`` and ``kl_mask_fraction`` (FOCOPS), ``kl`` (CUP);
    the ``"critics"`` objective has the critics' entries only.
    """
    views = batch.fields()
    out: dict[str, Tensor] = {}
    if not spec.critics_only:
        out.update(_policy_diagnostics(model, views, lam, spec))
    if not spec.actor_only:
        reward, cost = critic_losses(model, views)
        norm_reward, norm_cost = model.critic_squared_norms()
        out["loss_critic"] = reward + spec.critic_l2 * norm_reward
        out["loss_cost_critic"] = cost + spec.critic_l2 * norm_cost
    return out


def _policy_diagnostics(model: StackedActorCritic, views: Mapping[str, Tensor], lam: Tensor, spec: FirstOrderSpec,
                        ) -> dict[str, Tensor]:
    """The policy's entries of :func:`first_order_diagnostics`."""
    out = {"loss_objective": policy_loss(model, views, lam, spec)}
    loc, scale = model.dist_params(views["observation"])
    log_ratio = gaussian_log_prob(views["action"], loc, scale).unsqueeze(-1) - views["action_log_prob"]
    ratio = log_ratio.exp()
    out.update(kl_approx=(-log_ratio).mean((1, 2)), mean_ratio=ratio.mean((1, 2)), max_ratio=ratio.amax((1, 2)))
    if spec.objective == "ppo":
        clipped = log_ratio.clamp(*spec._clip_bounds)
        out["clip_fraction"] = (clipped != log_ratio).to(ratio.dtype).mean((1, 2))
    elif spec.objective == "focops":
        kl = gaussian_kl(loc, scale, views["loc"], views["scale"])
        out.update(kl=kl.mean(1), kl_mask_fraction=(kl <= spec.kl_threshold).to(kl.dtype).mean(1))
    elif spec.objective == "cup_projection":
        out["kl"] = gaussian_kl(loc, scale, views["stage1_loc"], views["stage1_scale"]).mean(1)
    return out


# ---------------------------------------------------------------------------- the step
class FusedFirstOrderStep:
    """One minibatch gradient step of SafePO's first-order loop for every seed of a group.

    ``step(batch, lam, active)``: the losses of :func:`policy_loss` and :func:`critic_losses` on the
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
        spec: what to compute.
        compile: run the losses (forward and their backward) through ``torch.compile``; when that
            fails (e.g. no C++ compiler) the step warns once, records :attr:`compile_error` and runs
            eagerly.
    """

    def __init__(self, model: StackedActorCritic, optimizer: SeedMaskedAdam, spec: FirstOrderSpec, *,
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
        self._losses = torch.compile(self._eager_losses, dynamic=False) if compile else self._eager_losses
        self.compile_error: str | None = None
        self._backward_seen = False

    @staticmethod
    def make_optimizer(model: StackedActorCritic, actor_lr: float, critic_lr: float, *,
                       max_grad_norm: float | None = 40.0, compile: bool = False, **adam) -> SeedMaskedAdam:
        """The trainer's optimiser for ``model``: actor group, critics group, per-seed clip at ``max_grad_norm``."""
        return SeedMaskedAdam([{"params": [model.flat_actor], "lr": actor_lr},
                               {"params": [model.flat_critics], "lr": critic_lr}],
                              max_grad_norm=max_grad_norm, compile=compile, **adam)

    def _eager_losses(self, data: Tensor, lam: Tensor, names: tuple[str, ...], widths: tuple[int, ...],
                      ) -> tuple[Tensor, ...]:
        views = dict(zip(names, torch.split(data, widths, dim=-1)))
        if self.spec.critics_only:
            return critic_losses(self.model, views)
        objective = policy_loss(self.model, views, lam, self.spec)
        if self.spec.actor_only:
            return (objective,)
        return (objective, *critic_losses(self.model, views))

    def backward(self, batch: SeedBatch, lam: Tensor) -> tuple[Tensor, ...]:
        """Gradients of the minibatch losses into the flat gradient buffers (zeroed first).

        Returns the per-seed losses, detached: ``(objective,)`` for an actor-only objective,
        ``(reward critic MSE, cost critic MSE)`` for ``"critics"``, else ``(objective, reward critic
        MSE, cost critic MSE)`` (the critics' without the L2 term, see :func:`first_order_diagnostics`).
        """
        missing = set(self.spec.fields) - set(batch.names)
        if missing:
            raise KeyError(f"the batch lacks {sorted(missing)} (fields: {batch.names})")
        model = self.model
        for index in self.groups:
            model.flat_groups[index].grad.zero_()
        losses = self._compute(batch, lam)
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

    def _compute(self, batch: SeedBatch, lam: Tensor) -> tuple[Tensor, ...]:
        try:
            return self._losses(batch.data, lam, batch.names, batch.widths)
        except Exception as error:  # noqa: BLE001 -- compiling failed: say so once, go on eagerly
            if self._losses == self._eager_losses:
                raise
            self.compile_error = f"{type(error).__name__}: {error}".splitlines()[0]
            warnings.warn(f"FusedFirstOrderStep: torch.compile failed, running eagerly ({self.compile_error})",
                          stacklevel=3)
            self._losses = self._eager_losses
            return self._losses(batch.data, lam, batch.names, batch.widths)

    def update(self, active: Tensor | None = None) -> Tensor | None:
        """The optimiser step on this objective's groups; returns each seed's gradient norm (or ``None``)."""
        return self.optimizer.step(active, groups=self.groups)

    def __call__(self, batch: SeedBatch, lam: Tensor, active: Tensor | None = None) -> tuple[Tensor, ...]:
        """:meth:`backward` then :meth:`update`; returns the detached per-seed losses."""
        losses = self.backward(batch, lam)
        self.update(active)
        return losses
