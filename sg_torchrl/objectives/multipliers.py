"""Lagrange multipliers for constrained policy optimisation.

A safe-RL loss such as :class:`~sg_torchrl.objectives.PPOLagLoss` turns the constrained problem

.. math::

    \\max_\\pi J_r(\\pi) \\quad \\text{s.t.} \\quad J_c(\\pi) \\le d

into the unconstrained Lagrangian :math:`J_r(\\pi) - \\lambda (J_c(\\pi) - d)` with a multiplier
:math:`\\lambda \\ge 0` that is adapted *outside* the loss, once per epoch, from the measured mean
episode cost :math:`J_c`. This module holds the multiplier update rules as small
:class:`torch.nn.Module` objects with one interface, :meth:`Multiplier.update`, so that a loss only
*reads* :attr:`Multiplier.value` and the trainer decides when to update it:

* :class:`LagrangeMultiplier`: projected gradient ascent on :math:`\\lambda` with Adam (Ray et al.
  2019, "Benchmarking Safe Exploration in Deep Reinforcement Learning"; the rule used by PPO-Lag,
  TRPO-Lag, RCPO, FOCOPS and CUP in SafePO and the Safety-Gymnasium paper, Ji et al. 2023).
* :class:`PIDLagrangeMultiplier`: the PID-controlled multiplier of Stooke, Achiam and Abbeel 2020,
  "Responsive Safety in Reinforcement Learning by PID Lagrangian Methods" (ICML 2020,
  https://arxiv.org/abs/2007.03964), used by CPPO-PID.

All state (optimiser moments, step counts, PID integral / EMAs / derivative history) lives in
registered buffers, so ``state_dict()`` / ``load_state_dict()`` restore a multiplier exactly and a
resumed run continues with bit-identical values. Hyper-parameters (learning rates, gains, bounds)
are constructor arguments, not state; only ``cost_limit`` is also kept as a buffer so that it
travels with checkpoints and devices.
"""
from __future__ import annotations

import abc
import math
from numbers import Real

import torch
from torch import nn, Tensor

from sg_torchrl.objectives.surrogates import combine_advantages, CombineRule

__all__ = ["Multiplier", "LagrangeMultiplier", "NoMultiplier", "PIDLagrangeMultiplier"]


def _as_finite_float(value: float | Tensor, name: str) -> float:
    """Converts a Python number or a one-element tensor to a finite Python float.

    Raises:
        ValueError: if ``value`` has more than one element or is NaN / infinite.
        TypeError: if ``value`` is neither a real number nor a tensor.
    """
    if isinstance(value, Tensor):
        if value.numel() != 1:
            raise ValueError(
                f"{name} must be a scalar (one element), got a tensor of shape {tuple(value.shape)}."
            )
        out = float(value.detach().reshape(()).item())
    elif isinstance(value, Real) and not isinstance(value, bool):
        out = float(value)
    else:
        raise TypeError(f"{name} must be a float or a one-element tensor, got {type(value).__name__}.")
    if not math.isfinite(out):
        raise ValueError(f"{name} must be finite, got {out}.")
    return out


def _check_non_negative(value: float, name: str) -> float:
    value = _as_finite_float(value, name)
    if value < 0:
        raise ValueError(f"{name} must be >= 0, got {value}.")
    return value


class Multiplier(nn.Module, abc.ABC):
    """Base class of the Lagrange-multiplier update rules.

    A multiplier keeps :math:`\\lambda \\ge 0` and moves it with the constraint violation
    :math:`J_c - d`, where :math:`J_c` is the measured mean episode cost and :math:`d` is
    ``cost_limit``. Losses read :attr:`value` (detached, never differentiated) and the trainer calls
    :meth:`update` once per epoch; the multiplier never owns a :class:`torch.optim.Optimizer`, so
    every piece of state is a buffer and checkpoints restore it exactly.

    Subclasses implement :meth:`update` and :meth:`_current_value`.

    Args:
        cost_limit (float): the constraint threshold :math:`d` (same units as the undiscounted
            episode cost). Stored as a ``float64`` buffer named ``cost_limit``.

    Attributes:
        sum_norm (bool): whether losses combine advantages as
            :math:`(A_r - \\lambda A_c) / (1 + \\lambda)` (``True``) or without the
            :math:`1 / (1 + \\lambda)` normalisation.
        diff_norm (bool): whether losses combine advantages as
            :math:`(1 - \\lambda) A_r - \\lambda A_c` with :math:`\\lambda \\in [0, 1]` (Stooke et al.
            2020's "diff_norm"). Takes precedence over ``sum_norm``.
    """

    sum_norm: bool = True
    diff_norm: bool = False
    cost_limit: Tensor

    def __init__(self, cost_limit: float = 25.0) -> None:
        super().__init__()
        cost_limit = _check_non_negative(cost_limit, "cost_limit")
        self.register_buffer("cost_limit", torch.tensor(cost_limit, dtype=torch.float64))

    @property
    def value(self) -> Tensor:
        """The current multiplier :math:`\\lambda \\ge 0` as a detached scalar tensor (a copy)."""
        return self._current_value().detach().clone()

    @abc.abstractmethod
    def _current_value(self) -> Tensor:
        """The multiplier as stored (no copy); implemented by subclasses."""

    @abc.abstractmethod
    def update(self, mean_episode_cost: float | Tensor) -> Tensor:
        """Moves the multiplier given the mean episode cost of the last epoch.

        Args:
            mean_episode_cost (float or Tensor): :math:`J_c`, the mean undiscounted episode cost
                measured during the epoch (a finite scalar).

        Returns:
            The new multiplier value (detached scalar tensor, >= 0).

        Raises:
            ValueError: if ``mean_episode_cost`` is not a finite scalar.
        """

    def violation(self, mean_episode_cost: float | Tensor) -> float:
        """:math:`J_c - d`: how far the measured mean episode cost is above the limit (negative below it).

        The one place the cost limit is subtracted: the multipliers' own updates, the trainer (which
        hands it to CPO / PCPO's step) and MACPO's constraint value all ask the multiplier, so the
        limit lives in this module alone.
        """
        return _as_finite_float(mean_episode_cost, "mean_episode_cost") - float(self.cost_limit)

    def forward(self) -> Tensor:
        """Returns :attr:`value`, so the module can be called like any other."""
        return self.value

    @property
    def combine_rule(self) -> CombineRule:
        """How :meth:`combine` mixes the advantages: ``"diff_norm"`` > ``"sum_norm"`` > ``"plain"``."""
        if self.diff_norm:
            return "diff_norm"
        return "sum_norm" if self.sum_norm else "plain"

    def combine(self, advantage: Tensor, cost_advantage: Tensor) -> Tensor:
        """The Lagrangian advantage every multiplier-based algorithm optimises.

        SafePO's :math:`(A_r - \\lambda A_c) / (1 + \\lambda)` when :attr:`sum_norm` (PPO-Lag,
        TRPO-Lag, RCPO, CPPO-PID, FOCOPS), :math:`(1 - \\lambda) A_r - \\lambda A_c` when
        :attr:`diff_norm` (Stooke et al. 2020) and :math:`A_r - \\lambda A_c` otherwise, with
        :math:`\\lambda` = :attr:`value` (no gradient flows into the multiplier):
        :func:`~sg_torchrl.objectives.surrogates.combine_advantages` with this multiplier's value and
        :attr:`combine_rule`, the function the seed-batched engine calls with one value per seed.

        Raises:
            ValueError: if the two advantages have different shapes (no silent broadcasting).
        """
        if advantage.shape != cost_advantage.shape:
            raise ValueError(
                f"the reward advantage has shape {tuple(advantage.shape)} but the cost advantage has shape "
                f"{tuple(cost_advantage.shape)}; they must match (no silent broadcasting)."
            )
        return combine_advantages(advantage, cost_advantage, self.value, self.combine_rule)


class NoMultiplier(Multiplier):
    """:math:`\\lambda = 0` for ever: the multiplier of the unconstrained baselines (PG, PPO, NPG, TRPO)
    and of CPO / PCPO, which handle the constraint in the policy step instead.

    Its :meth:`combine` returns the reward advantage, so an unconstrained algorithm is a Lagrangian
    loss with this multiplier rather than a second copy of the loss. The cost limit is kept for
    the algorithms that read it (CPO's :math:`c = J_c - d`).
    """

    def __init__(self, cost_limit: float = 25.0) -> None:
        super().__init__(cost_limit)
        self.register_buffer("_zero", torch.zeros((), dtype=torch.float32))

    def _current_value(self) -> Tensor:
        return self._zero

    def update(self, mean_episode_cost: float | Tensor) -> Tensor:
        _as_finite_float(mean_episode_cost, "mean_episode_cost")
        return self.value


class LagrangeMultiplier(Multiplier):
    """Lagrange multiplier learned by projected gradient ascent with Adam.

    This is the multiplier of PPO-Lag / TRPO-Lag (Ray et al. 2019, "Benchmarking Safe Exploration in
    Deep Reinforcement Learning") as implemented in SafePO and used for the Safety-Gymnasium paper's
    benchmarks (Ji et al. 2023, "Safety-Gymnasium: A Unified Safe Reinforcement Learning
    Benchmark"). A raw parameter :math:`\\tilde\\lambda` starts at ``max(init, 0)``; each call to
    :meth:`update` is one Adam step on the loss :math:`-\\tilde\\lambda (J_c - d)`, i.e. with the
    gradient :math:`-(J_c - d)`, so :math:`\\tilde\\lambda` grows while the constraint is violated and
    shrinks otherwise. After the step :math:`\\tilde\\lambda` is clamped to ``[0, upper_bound]``; the
    value used by losses is :math:`\\mathrm{relu}(\\tilde\\lambda)`.

    The Adam arithmetic is written out on buffers (``step``, ``exp_avg``, ``exp_avg_sq``) and is
    identical to :class:`torch.optim.Adam` with default settings (single-tensor code path, no
    weight decay, no AMSGrad), so no optimiser object has to be checkpointed next to the module.

    Args:
        cost_limit (float): constraint threshold :math:`d`. Defaults to ``25.0`` (paper value).
        init (float): initial multiplier; negative values are clamped to 0 as in SafePO.
            Defaults to ``0.001``.
        lr (float): Adam learning rate (> 0). Defaults to ``0.035`` (paper value).
        upper_bound (float, optional): clamp :math:`\\tilde\\lambda` to ``[0, upper_bound]`` after each
            step (SafePO uses 2.0 for FOCOPS and 0.2 for CUP). ``None`` (default) means no upper
            bound.
        betas (tuple of float): Adam's ``(beta1, beta2)``, each in ``[0, 1)``. Defaults to
            ``(0.9, 0.999)``.
        eps (float): Adam's ``eps`` (> 0). Defaults to ``1e-8``.
        sum_norm (bool): see :class:`Multiplier`. Defaults to ``True`` (SafePO's
            :math:`(A_r - \\lambda A_c) / (1 + \\lambda)`).

    Examples:
        >>> m = LagrangeMultiplier(cost_limit=25.0)
        >>> float(m.value)
        0.0010000000474974513
        >>> _ = m.update(40.0)  # constraint violated: lambda increases by ~lr
        >>> round(float(m.value), 4)
        0.036
    """

    lambda_raw: Tensor
    step: Tensor
    exp_avg: Tensor
    exp_avg_sq: Tensor

    def __init__(
        self,
        cost_limit: float = 25.0,
        init: float = 0.001,
        lr: float = 0.035,
        upper_bound: float | None = None,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        *,
        sum_norm: bool = True,
    ) -> None:
        super().__init__(cost_limit)
        init = _as_finite_float(init, "init")
        lr = _as_finite_float(lr, "lr")
        if lr <= 0:
            raise ValueError(f"lr must be > 0, got {lr}.")
        if upper_bound is not None:
            upper_bound = _check_non_negative(upper_bound, "upper_bound")
        if len(betas) != 2:
            raise ValueError(f"betas must be a pair (beta1, beta2), got {betas}.")
        beta1 = _as_finite_float(betas[0], "betas[0]")
        beta2 = _as_finite_float(betas[1], "betas[1]")
        for i, beta in enumerate((beta1, beta2)):
            if not 0.0 <= beta < 1.0:
                raise ValueError(f"betas[{i}] must be in [0, 1), got {beta}.")
        eps = _as_finite_float(eps, "eps")
        if eps <= 0:
            raise ValueError(f"eps must be > 0, got {eps}.")

        self.lr = lr
        self.upper_bound = upper_bound
        self.betas = (beta1, beta2)
        self.eps = eps
        self.sum_norm = bool(sum_norm)
        self.diff_norm = False
        # float32 like the torch parameter SafePO optimises, so the Adam arithmetic matches it.
        self.register_buffer("lambda_raw", torch.tensor(max(init, 0.0), dtype=torch.float32))
        self.register_buffer("step", torch.zeros((), dtype=torch.int64))
        self.register_buffer("exp_avg", torch.zeros((), dtype=torch.float32))
        self.register_buffer("exp_avg_sq", torch.zeros((), dtype=torch.float32))

    def _current_value(self) -> Tensor:
        return torch.relu(self.lambda_raw)

    @torch.no_grad()
    def update(self, mean_episode_cost: float | Tensor) -> Tensor:
        """One Adam step on :math:`-\\tilde\\lambda (J_c - d)`, then projection onto ``[0, upper_bound]``.

        Args:
            mean_episode_cost (float or Tensor): the mean episode cost :math:`J_c` of the epoch.

        Returns:
            The new multiplier value :math:`\\mathrm{relu}(\\tilde\\lambda)` (detached scalar tensor).
        """
        violation = self.violation(mean_episode_cost)
        # d/d(lambda) of -lambda * violation, in the parameter's dtype (as autograd would give it).
        grad = torch.tensor(-violation, dtype=self.lambda_raw.dtype, device=self.lambda_raw.device)
        beta1, beta2 = self.betas
        self.step += 1
        self.exp_avg.lerp_(grad, 1 - beta1)
        self.exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        step = float(self.step)
        bias_correction1 = 1 - beta1**step
        bias_correction2 = 1 - beta2**step
        step_size = self.lr / bias_correction1
        denom = (self.exp_avg_sq.sqrt() / bias_correction2**0.5).add_(self.eps)
        self.lambda_raw.addcdiv_(self.exp_avg, denom, value=-step_size)
        self.lambda_raw.clamp_(min=0.0, max=self.upper_bound)
        return self.value

    def extra_repr(self) -> str:
        return (
            f"cost_limit={float(self.cost_limit)}, lr={self.lr}, upper_bound={self.upper_bound}, "
            f"betas={self.betas}, eps={self.eps}, sum_norm={self.sum_norm}"
        )


class PIDLagrangeMultiplier(Multiplier):
    """PID-controlled Lagrange multiplier (CPPO-PID).

    Stooke, Achiam and Abbeel 2020, "Responsive Safety in Reinforcement Learning by PID Lagrangian
    Methods" (https://arxiv.org/abs/2007.03964) observe that gradient ascent on :math:`\\lambda` is
    an integral-only controller, which overshoots and oscillates; adding proportional and derivative
    terms damps the cost oscillations. With :math:`\\delta = J_c - d`, each :meth:`update` does

    * integral: :math:`I \\leftarrow \\max(0, I + K_i \\delta)` (also clamped to ``[0, 1]`` when
      ``diff_norm``), :math:`I` starting at ``init``;
    * proportional (EMA-smoothed error): :math:`P \\leftarrow \\alpha_p P + (1 - \\alpha_p) \\delta`;
    * derivative of the EMA-smoothed cost over ``d_delay`` updates:
      :math:`D \\leftarrow \\alpha_d D + (1 - \\alpha_d) J_c`,
      :math:`\\partial = \\max(0, D - D_{\\text{d\\_delay updates ago}})`, the history being a ring
      buffer of length ``d_delay`` initialised with zeros (only cost *increases* are penalised);
    * :math:`\\lambda = \\max(0, K_p P + I + K_d \\partial)`; clamped to ``[0, 1]`` if ``diff_norm``,
      or to ``[0, penalty_max]`` if neither ``sum_norm`` nor ``diff_norm`` is set.

    Defaults are SafePO's ``cppo_pid`` settings (the Safety-Gymnasium paper's hyper-parameters: Kp
    0.1, Ki 0.01, Kd 0.01), with the integral initialised from SafePO's
    ``--lagrangian-multiplier-init`` (0.001).

    .. note::
        Before the first :meth:`update`, :attr:`value` is ``init``. SafePO / OmniSafe start the
        penalty at 0 but always update the multiplier before the first policy update of an epoch,
        so that initial value is never used there; ``init`` is the consistent choice when a loss is
        evaluated before any update.

    The arithmetic is carried out in Python floats (IEEE double, like the reference controllers)
    and stored in ``float64`` buffers: ``integral``, ``p_ema``, ``d_ema``, ``d_history`` (length
    ``d_delay``), ``d_index`` (next ring-buffer slot), ``num_updates`` and ``multiplier``.

    Args:
        cost_limit (float): constraint threshold :math:`d`. Defaults to ``25.0``.
        kp (float): proportional gain (>= 0). Defaults to ``0.1``.
        ki (float): integral gain (>= 0). Defaults to ``0.01``.
        kd (float): derivative gain (>= 0). Defaults to ``0.01``.
        d_delay (int): number of updates over which the derivative is taken (>= 1). Defaults
            to ``10``.
        ema_alpha_p (float): EMA factor of the proportional error, in ``[0, 1]``. Defaults to
            ``0.95``.
        ema_alpha_d (float): EMA factor of the cost used by the derivative, in ``[0, 1]``. Defaults
            to ``0.95``.
        init (float): initial integral term and initial multiplier (>= 0). Defaults to ``0.001``.
        penalty_max (float): upper bound of :math:`\\lambda` when neither ``sum_norm`` nor
            ``diff_norm`` is set (> 0). Defaults to ``100.0``.
        sum_norm (bool): losses use :math:`(A_r - \\lambda A_c)/(1 + \\lambda)`. Defaults to ``True``.
        diff_norm (bool): losses use :math:`(1 - \\lambda) A_r - \\lambda A_c` and :math:`\\lambda`
            (and :math:`I`) are kept in ``[0, 1]``. Defaults to ``False``.

    Examples:
        >>> m = PIDLagrangeMultiplier(cost_limit=25.0)
        >>> float(m.value)
        0.001
        >>> round(float(m.update(45.0)), 4)  # I=0.201, P=1.0, D=2.25 -> 0.1*1 + 0.201 + 0.01*2.25
        0.3235
    """

    integral: Tensor
    p_ema: Tensor
    d_ema: Tensor
    d_history: Tensor
    d_index: Tensor
    num_updates: Tensor
    multiplier: Tensor

    def __init__(
        self,
        cost_limit: float = 25.0,
        kp: float = 0.1,
        ki: float = 0.01,
        kd: float = 0.01,
        d_delay: int = 10,
        ema_alpha_p: float = 0.95,
        ema_alpha_d: float = 0.95,
        init: float = 0.001,
        penalty_max: float = 100.0,
        sum_norm: bool = True,
        diff_norm: bool = False,
    ) -> None:
        super().__init__(cost_limit)
        self.kp = _check_non_negative(kp, "kp")
        self.ki = _check_non_negative(ki, "ki")
        self.kd = _check_non_negative(kd, "kd")
        if isinstance(d_delay, bool) or not isinstance(d_delay, int):
            raise TypeError(f"d_delay must be an int, got {type(d_delay).__name__}.")
        if d_delay < 1:
            raise ValueError(f"d_delay must be >= 1, got {d_delay}.")
        self.d_delay = d_delay
        for name, alpha in (("ema_alpha_p", ema_alpha_p), ("ema_alpha_d", ema_alpha_d)):
            alpha = _as_finite_float(alpha, name)
            if not 0.0 <= alpha <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {alpha}.")
        self.ema_alpha_p = float(ema_alpha_p)
        self.ema_alpha_d = float(ema_alpha_d)
        init = _check_non_negative(init, "init")
        penalty_max = _as_finite_float(penalty_max, "penalty_max")
        if penalty_max <= 0:
            raise ValueError(f"penalty_max must be > 0, got {penalty_max}.")
        self.penalty_max = penalty_max
        self.sum_norm = bool(sum_norm)
        self.diff_norm = bool(diff_norm)
        if self.diff_norm and init > 1.0:
            raise ValueError(f"init must be in [0, 1] when diff_norm=True, got {init}.")

        def scalar(x: float) -> Tensor:
            return torch.tensor(x, dtype=torch.float64)

        self.register_buffer("integral", scalar(init))
        self.register_buffer("p_ema", scalar(0.0))
        self.register_buffer("d_ema", scalar(0.0))
        self.register_buffer("d_history", torch.zeros(d_delay, dtype=torch.float64))
        self.register_buffer("d_index", torch.zeros((), dtype=torch.int64))
        self.register_buffer("num_updates", torch.zeros((), dtype=torch.int64))
        self.register_buffer("multiplier", scalar(init))

    def _current_value(self) -> Tensor:
        return self.multiplier

    @torch.no_grad()
    def update(self, mean_episode_cost: float | Tensor) -> Tensor:
        """One PID step from the mean episode cost of the epoch.

        Args:
            mean_episode_cost (float or Tensor): the mean episode cost :math:`J_c` of the epoch.

        Returns:
            The new multiplier value (detached ``float64`` scalar tensor).
        """
        jc = _as_finite_float(mean_episode_cost, "mean_episode_cost")
        delta = self.violation(jc)

        integral = max(0.0, float(self.integral) + self.ki * delta)
        if self.diff_norm:
            integral = min(1.0, integral)
        p_ema = self.ema_alpha_p * float(self.p_ema) + (1.0 - self.ema_alpha_p) * delta
        d_ema = self.ema_alpha_d * float(self.d_ema) + (1.0 - self.ema_alpha_d) * jc
        slot = int(self.d_index)
        derivative = max(0.0, d_ema - float(self.d_history[slot]))

        value = max(0.0, self.kp * p_ema + integral + self.kd * derivative)
        if self.diff_norm:
            value = min(1.0, value)
        elif not self.sum_norm:
            value = min(value, self.penalty_max)

        self.integral.fill_(integral)
        self.p_ema.fill_(p_ema)
        self.d_ema.fill_(d_ema)
        self.d_history[slot] = d_ema
        self.d_index.fill_((slot + 1) % self.d_delay)
        self.num_updates += 1
        self.multiplier.fill_(value)
        return self.value

    def extra_repr(self) -> str:
        return (
            f"cost_limit={float(self.cost_limit)}, kp={self.kp}, ki={self.ki}, kd={self.kd}, "
            f"d_delay={self.d_delay}, ema_alpha_p={self.ema_alpha_p}, "
            f"ema_alpha_d={self.ema_alpha_d}, penalty_max={self.penalty_max}, "
            f"sum_norm={self.sum_norm}, diff_norm={self.diff_norm}"
        )
