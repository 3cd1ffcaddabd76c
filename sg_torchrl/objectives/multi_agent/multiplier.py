"""MAPPO-Lagrangian's per-agent multiplier (Gu et al. 2023).

MAPPO-Lagrangian (Gu et al. 2023, "Safe multi-agent reinforcement learning for multi-robot
control", Artificial Intelligence 319; the MAPPO-Lag of the Safety-Gymnasium paper, Ji et al. 2023)
gives every agent :math:`i` its own multiplier :math:`\\lambda^i \\ge 0` for its own cost, optimises
the hybrid advantage :math:`A_r - \\lambda^i A^i_c` (no :math:`1/(1+\\lambda)` normalisation) and
moves :math:`\\lambda^i` by projected gradient steps on the linearised constraint of the *new*
policy,

.. math::

    \\delta^i = -\\Big[(J^i_c - d)(1 - \\gamma) + \\mathbb E\\big[r^i A^i_c\\big]\\Big], \\qquad
    \\lambda^i \\leftarrow \\mathrm{relu}(\\lambda^i - \\alpha\\, \\delta^i),

once after every minibatch step of agent :math:`i` (:math:`r^i` the agent's ratio at that step,
:math:`A^i_c` its standardised cost advantage, :math:`J^i_c` the mean episode cost of the rollout).

**Defaults.** The paper's hyper-parameter table lists "Lagrange init 1e-5, lr 0.78, SGD" and those
are the defaults here; SafePO's MaMuJoCo config runs ``lamda_lagr=0.78`` as the *initial*
multiplier and ``lagrangian_coef_rate=1e-5`` as the step size, with which :math:`\\lambda` stays
within about 1e-3 of 0.78 over a whole run (a fixed penalty). ``MAPPOLagMultiplier(init=0.78,
lr=1e-5)`` reproduces SafePO.
"""

from __future__ import annotations

import torch
from torch import Tensor

from sg_torchrl.objectives.multipliers import _as_finite_float, _check_non_negative, Multiplier

__all__ = ["MAPPOLagMultiplier"]


class MAPPOLagMultiplier(Multiplier):
    """One agent's MAPPO-Lagrangian multiplier: projected SGD on the linearised cost constraint.

    Losses combine advantages as :math:`A_r - \\lambda A_c` (``sum_norm=False``). See the module
    docstring for the rule and the defaults.

    Args:
        cost_limit (float): :math:`d`. Defaults to ``25.0``.
        init (float): initial :math:`\\lambda \\ge 0`. Defaults to ``1e-5`` (paper table).
        lr (float): SGD step :math:`\\alpha > 0`. Defaults to ``0.78`` (paper table).
        gamma (float): discount in the :math:`(1 - \\gamma)` scaling of :math:`J_c - d`. Defaults
            to ``0.99``.

    Examples:
        >>> m = MAPPOLagMultiplier(cost_limit=25.0)
        >>> round(float(m.update(125.0, cost_surrogate=0.0)), 4)  # 1e-5 + 0.78 * (100 * 0.01)
        0.78
    """

    multiplier: Tensor

    def __init__(self, cost_limit: float = 25.0, init: float = 1e-5, lr: float = 0.78, gamma: float = 0.99) -> None:
        super().__init__(cost_limit)
        self.lr = _as_finite_float(lr, "lr")
        if self.lr <= 0:
            raise ValueError(f"lr must be > 0, got {self.lr}.")
        self.gamma = _as_finite_float(gamma, "gamma")
        if not 0.0 <= self.gamma < 1.0:
            raise ValueError(f"gamma must be in [0, 1), got {self.gamma}.")
        self.sum_norm = False
        self.diff_norm = False
        self.register_buffer("multiplier", torch.tensor(_check_non_negative(init, "init"), dtype=torch.float64))

    def _current_value(self) -> Tensor:
        return self.multiplier

    @torch.no_grad()
    def update(self, mean_episode_cost: float | Tensor, cost_surrogate: float | Tensor = 0.0) -> Tensor:
        """:math:`\\lambda \\leftarrow \\mathrm{relu}(\\lambda + \\alpha [(J_c - d)(1 - \\gamma) + \\mathbb E[r A_c]])`.

        Args:
            mean_episode_cost: :math:`J_c`, the rollout's mean episode cost (of this agent).
            cost_surrogate: :math:`\\mathbb E[r A_c]` at the current minibatch step (the loss's
                ``cost_surrogate`` output). Defaults to ``0`` (the constraint value alone).

        Returns:
            The new multiplier (detached ``float64`` scalar).
        """
        surrogate = _as_finite_float(cost_surrogate, "cost_surrogate")
        f64 = dict(dtype=torch.float64)
        self.multiplier.copy_(self.step_rule(self.multiplier, torch.tensor(self.violation(mean_episode_cost), **f64),
                                             torch.tensor(surrogate, **f64), self.lr, self.gamma))
        return self.value

    @staticmethod
    def step_rule(value: Tensor, violation: Tensor, cost_surrogate: Tensor, lr: float | Tensor,
                  gamma: float | Tensor) -> Tensor:
        """The rule of :meth:`update` on ``float64`` tensors of any shape (one multiplier per entry):
        :math:`\mathrm{relu}(\lambda - \alpha \delta)`, :math:`\delta = -[(J_c - d)(1 - \gamma) + \mathbb E[r A_c]]`.

        ``violation``: :math:`J_c - d` (:meth:`violation`). The seed-batched round steps S agents' multipliers
        at once with it.
        """
        delta = -(violation * (1.0 - gamma) + cost_surrogate)
        return (value - lr * delta).clamp_min(0.0)

    def extra_repr(self) -> str:
        return f"cost_limit={float(self.cost_limit)}, lr={self.lr}, gamma={self.gamma}"
