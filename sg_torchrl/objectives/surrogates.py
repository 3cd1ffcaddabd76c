"""The first-order policy objectives, each written once, for any number of leading seed dimensions.

Every first-order algorithm of SafePO's family (PPO, PPO-Lag, CPPO-PID, PG, FOCOPS and CUP's two
stages) differs from the others in one per-sample expression: what it makes of the log importance
weight :math:`\\log r`, the advantage and, for FOCOPS and CUP, the KL to a stored policy. That
expression is a :class:`Surrogate` here, and it is the only place the expression is written:

* the TorchRL ``LossModule`` s (:class:`~sg_torchrl.objectives.PPOLagLoss` and its subclasses) call
  their :attr:`surrogate` on one batch (``seed_dims=0``: every dimension is a sample dimension);
* the seed-batched engine calls the same object on ``(S, minibatch, 1)`` tensors of S stacked seeds
  (``seed_dims=1``), through the :class:`SeedBatchedObjective` that the loss object hands it
  (:meth:`PPOLagLoss.seed_batched_objective`).

The Lagrangian mix of the two advantages (:func:`combine_advantages`) lives here too, for a
multiplier value per seed or one for all: :meth:`~sg_torchrl.objectives.Multiplier.combine` is this
function with the multiplier's own value and rule.

A :class:`SeedBatchedObjective` is a loss in the form the engine trains: the surrogate, the
advantage rule and the critics' L2 weight, evaluated on stacked networks (anything with
``dist_params(obs) -> (loc, scale)``, ``critic(obs)`` and ``cost_critic(obs)`` over ``(S, N, ...)``
inputs, e.g. :class:`~sg_torchrl.modules.stacked.StackedActorCritic`). Seed ``s`` of its losses is
exactly the LossModule's loss on seed ``s``'s minibatch.

Adding a first-order algorithm is one :class:`Surrogate` subclass and a loss that returns it (see
the README's "Add an algorithm").
"""
from __future__ import annotations

import abc
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import torch
from torch import Tensor

from sg_torchrl.modules.gaussian import gaussian_log_prob
from sg_torchrl.objectives.kl import gaussian_kl

__all__ = [
    "ClipSurrogate", "CombineRule", "CUPProjectionSurrogate", "FOCOPSSurrogate", "PGSurrogate",
    "SeedBatchedObjective", "Surrogate", "combine_advantages", "over_samples", "sample_mean",
]

CombineRule = Literal["sum_norm", "diff_norm", "plain"]
_COMBINE_RULES = ("sum_norm", "diff_norm", "plain")


def sample_mean(value: Tensor, seed_dims: int = 0, *, keepdim: bool = False) -> Tensor:
    """The mean over every dimension after the first ``seed_dims`` (one mean per seed; all for 0)."""
    if seed_dims == 0:
        return value.mean().reshape([1] * value.dim()) if keepdim else value.mean()
    return value.mean(tuple(range(seed_dims, value.dim())), keepdim=keepdim)


def over_samples(lam: Tensor, like: Tensor) -> Tensor:
    """``lam`` (0-d, or one value per seed ``(S,)``) detached, in ``like``'s dtype, shaped to broadcast over ``like``'s samples."""
    lam = lam.detach().to(device=like.device, dtype=like.dtype)
    return lam.view(-1, *([1] * (like.dim() - 1))) if lam.dim() else lam


def combine_advantages(advantage: Tensor, cost_advantage: Tensor, lam: Tensor, rule: CombineRule) -> Tensor:
    """The Lagrangian advantage: SafePO's :math:`(A_r - \\lambda A_c) / (1 + \\lambda)` (``"sum_norm"``),
    :math:`(1 - \\lambda) A_r - \\lambda A_c` (``"diff_norm"``, Stooke et al. 2020) or
    :math:`A_r - \\lambda A_c` (``"plain"``).

    ``lam`` is one value (0-d) or one per seed (``(S,)``, broadcast over the samples of
    ``(S, ...)`` advantages); it is cast to the advantages' dtype and carries no gradient.
    """
    lam = over_samples(lam, advantage)
    if rule == "diff_norm":
        return (1 - lam) * advantage - lam * cost_advantage
    if rule == "sum_norm":
        return (advantage - lam * cost_advantage) / (1 + lam)
    if rule == "plain":
        return advantage - lam * cost_advantage
    raise ValueError(f"unknown combine rule {rule!r}; expected one of {_COMBINE_RULES}")


# ---------------------------------------------------------------------------- surrogates
class Surrogate(abc.ABC):
    """One first-order policy objective: the per-sample loss made of :math:`\\log r`, :math:`A` (and a KL).

    Class attributes say what the objective reads, so the callers fetch exactly that:

    * :attr:`advantage`: what :meth:`loss` receives as ``advantage``: ``"combined"`` (the
      multiplier's mix of :math:`A_r` and :math:`A_c`), ``"reward"`` (:math:`A_r` itself, for an
      objective that treats the cost term its own way; :math:`A_c` always comes as
      ``cost_advantage``) or ``"cost"`` (:math:`A_c` alone, CUP's projection);
    * :attr:`reference`: ``None``, or the stored policy the objective's KL goes to: ``"rollout"``
      (the behaviour policy's ``loc`` / ``scale``, FOCOPS) or ``"stage1"`` (CUP's stage-one policy);
    * :attr:`trains_critics`: whether the critics learn in the same gradient steps;
    * :attr:`diagnostic_names`: the keys of :meth:`diagnostics`.

    Every tensor is ``(*seeds, *samples, 1)``; ``seed_dims`` says how many leading dimensions are
    seeds (0 for one batch, 1 for a seed group). :meth:`loss` returns the per-sample loss (the
    caller reduces it); only objectives that take a statistic over the batch (FOCOPS's SafePO
    broadcast) use ``seed_dims`` there.
    """

    advantage: ClassVar[Literal["combined", "reward", "cost"]] = "combined"
    reference: ClassVar[Literal["rollout", "stage1"] | None] = None
    trains_critics: ClassVar[bool] = True
    diagnostic_names: ClassVar[tuple[str, ...]] = ()

    @abc.abstractmethod
    def loss(self, log_weight: Tensor, advantage: Tensor, *, cost_advantage: Tensor | None = None,
             kl: Tensor | None = None, lam: Tensor | None = None, log_is_weight: Tensor | None = None,
             seed_dims: int = 0) -> Tensor:
        """The per-sample loss (the negated surrogate), differentiable in ``log_weight`` (and ``kl``).

        Args:
            log_weight: :math:`\\log \\pi_\\theta(a|s) - \\log \\pi_{\\text{prox}}(a|s)`.
            advantage: the advantage of :attr:`advantage`, same shape.
            cost_advantage: :math:`A_c`, same shape.
            kl: per-sample :math:`\\mathrm{KL}(\\pi_\\theta \\| \\pi_{\\text{ref}})` when
                :attr:`reference` is set.
            lam: the multiplier's value, 0-d or one per seed (read by objectives that weight a
                term by it, CUP's :math:`\\nu`).
            log_is_weight: TorchRL's importance correction :math:`\\log \\pi_{\\text{prox}} -
                \\log \\pi_{\\text{behav}}` (``None``: the proximal policy is the behaviour policy).
            seed_dims: how many leading dimensions are seeds.
        """

    def diagnostics(self, log_weight: Tensor, *, kl: Tensor | None = None, seed_dims: int = 0) -> dict[str, Tensor]:
        """Detached per-seed diagnostics (scalars for ``seed_dims=0``), keyed by :attr:`diagnostic_names`."""
        return {}

    @staticmethod
    def log_ratio(log_weight: Tensor, log_is_weight: Tensor | None) -> Tensor:
        """:math:`\\log \\pi_\\theta / \\pi_{\\text{behav}}`, the log importance weight to the rollout policy."""
        return log_weight if log_is_weight is None else log_weight + log_is_weight


@dataclass(frozen=True)
class ClipSurrogate(Surrogate):
    """PPO's clipped surrogate :math:`-\\min(r A, \\mathrm{clip}(r, 1 - \\epsilon, 1 + \\epsilon) A)`.

    The objective of PPO, PPO-Lag, CPPO-PID and CUP's first stage. The clip is applied to the log
    weight, at :math:`\\log(1 \\pm \\epsilon)` computed in float32 (TorchRL's ``ClipPPOLoss``);
    ``clip_epsilon_high`` makes the upper bound :math:`\\log(1 + \\epsilon_{\\text{high}})`.
    """

    clip_epsilon: float = 0.2
    clip_epsilon_high: float | None = None
    bounds: tuple[float, float] = field(init=False, repr=False, compare=False)
    diagnostic_names: ClassVar[tuple[str, ...]] = ("clip_fraction",)

    def __post_init__(self) -> None:
        low = torch.tensor(float(self.clip_epsilon), dtype=torch.float32)
        high = low if self.clip_epsilon_high is None else torch.tensor(float(self.clip_epsilon_high), dtype=torch.float32)
        object.__setattr__(self, "bounds", ((-low).log1p().item(), high.log1p().item()))

    def loss(self, log_weight, advantage, *, cost_advantage=None, kl=None, lam=None, log_is_weight=None, seed_dims=0):
        clipped = log_weight.clamp(*self.bounds)
        if log_is_weight is not None:
            clipped = clipped + log_is_weight
        ratio = self.log_ratio(log_weight, log_is_weight).exp()
        return -torch.minimum(ratio * advantage, clipped.exp() * advantage)

    def diagnostics(self, log_weight, *, kl=None, seed_dims=0):
        clipped = log_weight.clamp(*self.bounds)
        return {"clip_fraction": sample_mean((clipped != log_weight).to(log_weight.dtype), seed_dims)}


@dataclass(frozen=True)
class PGSurrogate(Surrogate):
    """The importance-weighted policy gradient :math:`-r A` (SafePO's PG), no clip."""

    def loss(self, log_weight, advantage, *, cost_advantage=None, kl=None, lam=None, log_is_weight=None, seed_dims=0):
        return -self.log_ratio(log_weight, log_is_weight).exp() * advantage


@dataclass(frozen=True)
class FOCOPSSurrogate(Surrogate):
    """FOCOPS (Zhang et al. 2020): :math:`(\\mathrm{KL}_i - r_i A_i / \\lambda_F)\\,\\mathbb 1\\{\\mathrm{KL}_i \\le \\delta\\}`.

    ``KL_i`` goes from the current policy to the rollout policy; the indicator carries no gradient.
    With ``safepo_broadcast`` the indicator only scales the advantage term by the seed's fraction
    of samples inside the trust region (SafePO's broadcasting quirk; see ``FOCOPSLoss``).
    """

    temperature: float = 1.5
    kl_threshold: float = 0.02
    safepo_broadcast: bool = False
    reference: ClassVar[str] = "rollout"
    diagnostic_names: ClassVar[tuple[str, ...]] = ("kl", "kl_mask_fraction")

    def loss(self, log_weight, advantage, *, cost_advantage=None, kl=None, lam=None, log_is_weight=None, seed_dims=0):
        inside = (kl.detach() <= self.kl_threshold).to(kl.dtype)
        weighted_gain = self.log_ratio(log_weight, log_is_weight).exp() * advantage / self.temperature
        if self.safepo_broadcast:
            return kl * inside - sample_mean(inside, seed_dims, keepdim=True) * weighted_gain
        return (kl - weighted_gain) * inside

    def diagnostics(self, log_weight, *, kl=None, seed_dims=0):
        kl = kl.detach()
        return {"kl": sample_mean(kl, seed_dims),
                "kl_mask_fraction": sample_mean((kl <= self.kl_threshold).to(kl.dtype), seed_dims)}


@dataclass(frozen=True)
class CUPProjectionSurrogate(Surrogate):
    """CUP's projection (stage two): :math:`\\nu c\\, r A_c + \\mathrm{KL}(\\pi_\\theta \\| \\pi_{\\text{stage1}})`.

    ``cost_coeff`` is :math:`c = (1 - \\gamma\\lambda) / (1 - \\gamma)`, :math:`\\nu` the multiplier's
    value; the actor alone learns (Yang et al. 2022; see ``CUPLoss``).
    """

    cost_coeff: float = 5.95
    advantage: ClassVar[str] = "cost"
    reference: ClassVar[str] = "stage1"
    trains_critics: ClassVar[bool] = False
    diagnostic_names: ClassVar[tuple[str, ...]] = ("kl",)

    def loss(self, log_weight, advantage, *, cost_advantage=None, kl=None, lam=None, log_is_weight=None, seed_dims=0):
        ratio = self.log_ratio(log_weight, log_is_weight).exp()
        return over_samples(lam, log_weight) * self.cost_coeff * ratio * advantage + kl

    def diagnostics(self, log_weight, *, kl=None, seed_dims=0):
        return {"kl": sample_mean(kl.detach(), seed_dims)}


# ---------------------------------------------------------------------------- the engine's form
#: The batch fields of the stored policy each :attr:`Surrogate.reference` reads.
REFERENCE_FIELDS: Mapping[str, tuple[str, str]] = {"rollout": ("loc", "scale"), "stage1": ("stage1_loc", "stage1_scale")}


@dataclass(frozen=True)
class SeedBatchedObjective:
    """A first-order loss in the form the seed-batched engine trains: S seeds' losses from one pass.

    Obtained from the loss object (:meth:`PPOLagLoss.seed_batched_objective`), never built from an
    algorithm's name.

    Attributes:
        surrogate: the policy objective; ``None`` for the critics alone (the minibatch passes of the
            second-order algorithms, whose actor moves by a trust-region step).
        combine: how the multiplier mixes the advantages (:func:`combine_advantages`).
        critic_l2: weight of ``sum(p ** 2)`` over each critic's parameters (0: none); the engine
            adds its gradient in closed form, :meth:`diagnostics` its value.
    """

    surrogate: Surrogate | None
    combine: CombineRule = "sum_norm"
    critic_l2: float = 1e-3

    def __post_init__(self) -> None:
        if self.surrogate is not None and not isinstance(self.surrogate, Surrogate):
            raise TypeError(f"surrogate must be a Surrogate or None, got {type(self.surrogate).__name__}")
        if self.combine not in _COMBINE_RULES:
            raise ValueError(f"unknown combine rule {self.combine!r}; expected one of {_COMBINE_RULES}")

    @property
    def critics_only(self) -> bool:
        """Whether only the critics learn (the second-order algorithms' minibatch passes)."""
        return self.surrogate is None

    @property
    def actor_only(self) -> bool:
        """Whether only the actor learns (CUP's projection)."""
        return self.surrogate is not None and not self.surrogate.trains_critics

    @property
    def groups(self) -> tuple[int, ...]:
        """The optimiser groups a step moves: 0 the actor, 1 the critics."""
        if self.actor_only:
            return (0,)
        return (1,) if self.critics_only else (0, 1)

    @property
    def num_losses(self) -> int:
        """How many per-seed losses :meth:`losses` returns: the objective (unless critics only), then each critic's."""
        return (0 if self.critics_only else 1) + (0 if self.actor_only else 2)

    @property
    def kl_stop(self) -> bool:
        """Whether the passes stop on the policy's KL (SafePO's early stop); not when only the critics move."""
        return not self.critics_only

    @property
    def fields(self) -> tuple[str, ...]:
        """The per-sample batch fields the losses read."""
        critics = ("value_target", "cost_value_target")
        if self.surrogate is None:
            return ("observation", *critics)
        advantages = ("cost_advantage",) if self.surrogate.advantage == "cost" else ("advantage", "cost_advantage")
        reference = REFERENCE_FIELDS[self.surrogate.reference] if self.surrogate.reference else ()
        names = ("observation", "action", "action_log_prob", *advantages, *reference)
        return names + (critics if self.surrogate.trains_critics else ())

    # ---------------------------------------------------------------- losses
    def _policy_terms(self, model, batch: Mapping[str, Tensor]) -> tuple[Tensor, Tensor | None]:
        """The log importance weight and (if the surrogate has a reference policy) the KL to it, one actor pass."""
        loc, scale = model.dist_params(batch["observation"])
        log_weight = gaussian_log_prob(batch["action"], loc, scale).unsqueeze(-1) - batch["action_log_prob"]
        kl = None
        if self.surrogate.reference is not None:
            ref_loc, ref_scale = (batch[name] for name in REFERENCE_FIELDS[self.surrogate.reference])
            kl = gaussian_kl(loc, scale, ref_loc, ref_scale).unsqueeze(-1)
        return log_weight, kl

    def _objective(self, log_weight: Tensor, kl: Tensor | None, batch: Mapping[str, Tensor], lam: Tensor) -> Tensor:
        """Each seed's mean surrogate loss from the actor's terms, ``(S,)``."""
        cost_advantage = batch["cost_advantage"]
        if self.surrogate.advantage == "cost":
            advantage = cost_advantage
        elif self.surrogate.advantage == "reward":
            advantage = batch["advantage"]
        else:
            advantage = combine_advantages(batch["advantage"], cost_advantage, lam, self.combine)
        return self.surrogate.loss(log_weight, advantage, cost_advantage=cost_advantage, kl=kl, lam=lam,
                                   seed_dims=1).mean((1, 2))

    @staticmethod
    def critic_losses(model, batch: Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
        """Each seed's reward- and cost-critic MSE to the targets, ``(S,)`` each, without the L2 term."""
        obs = batch["observation"]
        value = model.critic(obs)
        cost_value = model.cost_critic(obs)
        return (((value - batch["value_target"]) ** 2).mean((1, 2)),
                ((cost_value - batch["cost_value_target"]) ** 2).mean((1, 2)))

    def losses(self, model, batch: Mapping[str, Tensor], lam: Tensor) -> tuple[Tensor, ...]:
        """The per-seed losses a gradient step sums: ``(objective?, reward critic?, cost critic?)``, ``(S,)`` each.

        ``(objective,)`` for an actor-only surrogate, the two critics' MSE for ``surrogate=None``,
        else all three. ``batch`` holds ``(S, mb, width)`` fields, ``lam`` each seed's multiplier value ``(S,)``.
        """
        if self.critics_only:
            return self.critic_losses(model, batch)
        objective = self._objective(*self._policy_terms(model, batch), batch, lam)
        if self.actor_only:
            return (objective,)
        return (objective, *self.critic_losses(model, batch))

    @torch.no_grad()
    def diagnostics(self, model, batch: Mapping[str, Tensor], lam: Tensor) -> dict[str, Tensor]:
        """Per-seed ``(S,)`` diagnostics of one minibatch under the LossModule's names.

        ``loss_objective``, ``kl_approx`` (mean log old / new), ``mean_ratio``, ``max_ratio`` and
        the surrogate's own, and ``loss_critic`` / ``loss_cost_critic`` with their L2 term.
        """
        out: dict[str, Tensor] = {}
        if not self.critics_only:
            log_weight, kl = self._policy_terms(model, batch)  # one actor pass for the loss and its diagnostics
            out["loss_objective"] = self._objective(log_weight, kl, batch, lam)
            ratio = log_weight.exp()
            out.update(kl_approx=(-log_weight).mean((1, 2)), mean_ratio=ratio.mean((1, 2)),
                       max_ratio=ratio.amax((1, 2)))
            out.update(self.surrogate.diagnostics(log_weight, kl=kl, seed_dims=1))
        if not self.actor_only:
            reward, cost = self.critic_losses(model, batch)
            norm_reward, norm_cost = model.critic_squared_norms()
            out["loss_critic"] = reward + self.critic_l2 * norm_reward
            out["loss_cost_critic"] = cost + self.critic_l2 * norm_cost
        return out
