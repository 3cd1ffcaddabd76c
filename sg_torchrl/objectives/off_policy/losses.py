"""SAC-Lag, TD3-Lag and DDPG-Lag: TorchRL's ``SACLoss``, ``TD3Loss`` and ``DDPGLoss`` with a cost critic and a multiplier.

Each class subclasses the TorchRL loss and keeps what it builds (functional parameters, target
parameters that TorchRL's ``SoftUpdate`` / ``HardUpdate`` find, the tensordict keys of ``set_keys``, the
value estimator's ``gamma`` from ``make_value_estimator``) and adds

* a cost critic ``cost_qvalue_network`` (twin where the reward critic is: SAC and TD3 two, DDPG one),
  with its own target parameters ``target_cost_qvalue_network_params``, reading the ``"cost"`` entry
  (``set_keys(cost=...)``) as the reward critic reads ``"reward"``;
* an optional multiplier (:class:`~sg_torchrl.objectives.LagrangeMultiplier`,
  :class:`~sg_torchrl.objectives.PIDLagrangeMultiplier`), whose value the actor loss reads; the trainer
  calls ``multiplier.update(mean_episode_cost)`` once per epoch.

Without a multiplier (and cost critic) a class is the unconstrained algorithm itself, TorchRL's loss
to float rounding (``tests/test_off_policy_losses.py``): SAC, TD3 and DDPG are these classes with
``multiplier=None``, and SAC-PID, TD3-PID, DDPG-PID the same classes with the PID multiplier.

The math of every loss is :class:`~sg_torchrl.objectives.off_policy.objective.OffPolicyObjective`, the
form the seed-group engine trains (``loss.seed_batched_objective()``); ``forward`` evaluates the
functional networks on the batch and hands their outputs to it. The value estimator is TD(0) (a one-step
target; TD(lambda) would need whole trajectories, which a replay buffer's transitions are not).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules.distributions.utils import rsample_and_log_prob
from torchrl.objectives import DDPGLoss, SACLoss, TD3Loss
from torchrl.objectives.utils import ValueEstimators

from sg_torchrl.objectives.multipliers import Multiplier
from sg_torchrl.objectives.off_policy.objective import OffPolicyObjective

__all__ = ["DDPGLagLoss", "SACLagLoss", "TD3LagLoss"]


class _CostCritic:
    """What the three losses add to their TorchRL base: the cost critic, the multiplier and the one ``forward``.

    A subclass says how its actor acts (:meth:`_actor_action`), which action the targets are taken at
    (:meth:`_next_action`) and which parameters its reward critics are (:attr:`_critic_params`).
    """

    multiplier: Multiplier | None
    cost_qvalue_network: nn.Module
    cost_qvalue_network_params: TensorDictBase
    target_cost_qvalue_network_params: TensorDictBase

    def _init_constraint(self, cost_qvalue_network, multiplier: Multiplier | None, num_nets: int,
                         cost_reduction: str) -> None:
        if (cost_qvalue_network is None) != (multiplier is None):
            raise ValueError("give a cost critic and a multiplier together (SAC-Lag, ...), or neither (SAC, ...)")
        if multiplier is not None and not isinstance(multiplier, Multiplier):
            raise TypeError(f"multiplier must be a sg_torchrl Multiplier, got {type(multiplier).__name__}")
        self.multiplier = multiplier
        self.cost_reduction = cost_reduction
        self.num_cost_qvalue_nets = num_nets
        if cost_qvalue_network is not None:
            self.convert_to_functional(cost_qvalue_network, "cost_qvalue_network", num_nets if num_nets > 1 else None,
                                       create_target_params=True)
        self._set_in_keys()
        self.seed_batched_objective()  # refuses bad options now rather than at the first batch

    @property
    def constrained(self) -> bool:
        return self.multiplier is not None

    @property
    def discount(self) -> float:
        """The discount, the value estimator's (``make_value_estimator(gamma=...)``; TorchRL's default 0.99)."""
        return float(self.value_estimator.gamma)

    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        """TorchRL's ``make_value_estimator``, TD(0) only: the cost target is the same one-step bootstrap."""
        if value_type not in (None, ValueEstimators.TD0):
            raise ValueError(f"{type(self).__name__} takes the TD(0) value estimator only, got {value_type}")
        return super().make_value_estimator(value_type, **hyperparams)

    def _extra_in_keys(self) -> set:
        keys = set()
        if self.constrained:
            keys.add(("next", self.tensor_keys.cost))
            keys.update(self.cost_qvalue_network.in_keys)
        return keys

    def _set_in_keys(self):
        super()._set_in_keys()
        if getattr(self, "multiplier", None) is not None:
            self._in_keys = sorted(set(self._in_keys) | self._extra_in_keys(), key=str)

    # ------------------------------------------------------------------ networks
    def _q_values(self, network: nn.Module, params: TensorDictBase, tensordict: TensorDictBase,
                  action: Tensor) -> Tensor:
        """``network`` (a Q-network) with each of the parameter sets ``params`` at ``(s, action)``: ``(K, *batch)``."""
        td = tensordict.select(*network.in_keys, strict=False).copy()
        td.set(self.tensor_keys.action, action)
        sets = [params] if params.batch_dims == 0 else [params[k] for k in range(params.batch_size[0])]
        values = []
        for one in sets:
            with one.to_module(network):
                values.append(network(td.copy()).get(self.tensor_keys.state_action_value).squeeze(-1))
        return torch.stack(values)

    def _critic_outputs(self, tensordict: TensorDictBase, action: Tensor, *, target: bool, detach: bool = False,
                        ) -> tuple[Tensor, Tensor | None]:
        """The reward critics' and (constrained) cost critics' values at ``(s, action)``."""
        params = self._target_critic_params if target else self._critic_params
        q = self._q_values(self._critic_network, params.detach() if detach else params, tensordict, action)
        if not self.constrained:
            return q, None
        cost_params = self.target_cost_qvalue_network_params if target else self.cost_qvalue_network_params
        cost_q = self._q_values(self.cost_qvalue_network, cost_params.detach() if detach else cost_params,
                                tensordict, action)
        return q, cost_q

    # ------------------------------------------------------------------ the loss
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Every loss on a batch of transitions (the objective's :meth:`~OffPolicyObjective.losses`).

        Reads ``observation``, ``action``, ``("next", "observation")``, ``("next", "reward")``,
        ``("next", "terminated")`` and, constrained, ``("next", "cost")``. Returns ``loss_actor``,
        ``loss_qvalue`` (the reward critics, summed over the twins), and constrained ``loss_cost_qvalue`` and
        ``lagrangian`` (the multiplier); SAC adds ``loss_alpha``, ``alpha`` and ``entropy``; every loss
        also reports ``pred_value`` / ``target_value`` (and the cost critics').
        """
        keys = self.tensor_keys
        next_td = tensordict.get("next")
        with torch.no_grad():
            next_action, next_log_prob = self._next_action(tensordict)
            next_q, next_cost_q = self._critic_outputs(next_td, next_action, target=True)
        q, cost_q = self._critic_outputs(tensordict, tensordict.get(keys.action), target=False)
        action, log_prob = self._actor_action(tensordict)
        actor_q, actor_cost_q = self._critic_outputs(tensordict, action, target=False, detach=True)
        objective = self.seed_batched_objective()
        lam = self.multiplier.value if self.constrained else None
        out = objective.losses(
            q=q, next_q=next_q, reward=next_td.get(keys.reward).squeeze(-1),
            terminated=next_td.get(keys.terminated).squeeze(-1), seed_dims=0, next_log_prob=next_log_prob,
            cost_q=cost_q, next_cost_q=next_cost_q,
            cost=next_td.get(keys.cost).squeeze(-1) if self.constrained else None,
            actor_q=actor_q, actor_log_prob=log_prob, actor_cost_q=actor_cost_q, lam=lam)
        result = {name: out[name] for name in ("loss_actor", "loss_qvalue")}
        result.update(pred_value=q.detach(), target_value=out["target_value"])
        if self.constrained:
            result.update(loss_cost_qvalue=out["loss_cost_qvalue"], pred_cost_value=cost_q.detach(),
                          target_cost_value=out["target_cost_value"], lagrangian=lam)
        result.update(self._extra_outputs(log_prob))
        return TensorDict(result, batch_size=[])

    def _extra_outputs(self, log_prob: Tensor | None) -> dict[str, Tensor]:
        return {}

    def _check_reduction(self, reduction: str | None) -> None:
        if reduction not in (None, "mean"):
            raise ValueError(f"{type(self).__name__} averages its losses over the batch (reduction 'mean'), "
                             f"got reduction={reduction!r}")


class SACLagLoss(_CostCritic, SACLoss):
    """SAC (``multiplier=None``), SAC-Lag (a ``LagrangeMultiplier``) or SAC-PID (a ``PIDLagrangeMultiplier``).

    TorchRL's ``SACLoss`` (version 2: no state-value network) with a fixed :math:`\\alpha` (OmniSafe's SAC-Lag
    default, ``alpha_init=0.2``), plus a twin cost critic. Next actions for both targets are sampled from
    the current policy; the cost target has no entropy term.

    Args:
        actor_network, qvalue_network: as ``SACLoss`` (a list of ``num_qvalue_nets`` critics keeps each one's
            initialisation).
        cost_qvalue_network: the cost critic (or a list of ``num_qvalue_nets``), writing ``"state_action_value"``.
        multiplier: the multiplier; ``None`` (with no cost critic): SAC.
        cost_reduction: how the twin cost critics are reduced, ``"max"`` (default), ``"mean"`` or ``"min"``
            (:mod:`~sg_torchrl.objectives.off_policy.objective`).
        loss_function: the critics' regression loss (OmniSafe's ``"l2"``; TorchRL's default is ``"smooth_l1"``).
        **kwargs: ``SACLoss``'s other options (an unknown one is refused by ``SACLoss``).

    Raises:
        ValueError: ``fixed_alpha=False`` or a state-value network (this loss's engine form has neither), a
            reduction other than the mean, a cost critic without a multiplier or the reverse.
    """

    @dataclass
    class _AcceptedKeys(SACLoss._AcceptedKeys):
        """``SACLoss``'s keys and ``cost``: the per-step cost, read under ``"next"`` as the reward."""

        cost: NestedKey = "cost"

    default_keys = _AcceptedKeys

    def __init__(self, actor_network, qvalue_network, cost_qvalue_network=None, multiplier: Multiplier | None = None,
                 *, cost_reduction: str = "max", num_qvalue_nets: int = 2, loss_function: str = "l2",
                 alpha_init: float = 0.2, fixed_alpha: bool = True, value_network=None, reduction: str | None = None,
                 **kwargs) -> None:
        if not fixed_alpha:
            raise ValueError("SACLagLoss trains with a fixed alpha (fixed_alpha=True, OmniSafe's default)")
        if value_network is not None:
            raise ValueError("SACLagLoss is SAC version 2: no state-value network")
        self._check_reduction(reduction)
        super().__init__(actor_network, qvalue_network, num_qvalue_nets=num_qvalue_nets, loss_function=loss_function,
                         alpha_init=alpha_init, fixed_alpha=True, **kwargs)
        self._init_constraint(cost_qvalue_network, multiplier, num_qvalue_nets, cost_reduction)

    _critic_network = property(lambda self: self.qvalue_network)
    _critic_params = property(lambda self: self.qvalue_network_params)
    _target_critic_params = property(lambda self: self.target_qvalue_network_params)

    @property
    def alpha(self) -> float:
        """The fixed entropy weight."""
        return float(self.log_alpha.exp())

    def seed_batched_objective(self) -> OffPolicyObjective:
        """This loss's math for S stacked seeds (the engine's form; ``forward`` evaluates the same object)."""
        return OffPolicyObjective(gamma=self.discount, alpha=self.alpha, actor_q="min", cost_reduction=self.cost_reduction,
                                  loss_function=self.loss_function, constrained=self.constrained)

    def _sample(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor]:
        with set_exploration_type(ExplorationType.RANDOM), self.actor_network_params.to_module(self.actor_network):
            return rsample_and_log_prob(self.actor_network.get_dist(tensordict))

    def _next_action(self, tensordict):
        return self._sample(tensordict.get("next"))

    def _actor_action(self, tensordict):
        return self._sample(tensordict)

    def _extra_outputs(self, log_prob):
        return {"loss_alpha": self.alpha_loss(log_prob.detach()).mean(), "alpha": self.log_alpha.exp().detach(),
                "entropy": -log_prob.detach().mean()}


class TD3LagLoss(_CostCritic, TD3Loss):
    """TD3 (``multiplier=None``), TD3-Lag or TD3-PID: TorchRL's ``TD3Loss`` plus a twin cost critic.

    Both targets are taken at the target actor's action with clipped smoothing noise (``policy_noise``,
    ``noise_clip``); the actor maximises the first reward critic (TorchRL's and the paper's TD3).

    Args:
        actor_network, qvalue_network, action_spec / bounds: as ``TD3Loss``.
        cost_qvalue_network, multiplier, cost_reduction, loss_function: as :class:`SACLagLoss`.
        **kwargs: ``TD3Loss``'s other options.
    """

    @dataclass
    class _AcceptedKeys(TD3Loss._AcceptedKeys):
        """``TD3Loss``'s keys and ``cost``."""

        cost: NestedKey = "cost"

    default_keys = _AcceptedKeys

    def __init__(self, actor_network, qvalue_network, cost_qvalue_network=None, multiplier: Multiplier | None = None,
                 *, cost_reduction: str = "max", num_qvalue_nets: int = 2, loss_function: str = "l2",
                 reduction: str | None = None, **kwargs) -> None:
        self._check_reduction(reduction)
        super().__init__(actor_network, qvalue_network, num_qvalue_nets=num_qvalue_nets, loss_function=loss_function,
                         **kwargs)
        self._init_constraint(cost_qvalue_network, multiplier, num_qvalue_nets, cost_reduction)

    _critic_network = property(lambda self: self.qvalue_network)
    _critic_params = property(lambda self: self.qvalue_network_params)
    _target_critic_params = property(lambda self: self.target_qvalue_network_params)

    def seed_batched_objective(self) -> OffPolicyObjective:
        """This loss's math for S stacked seeds (the engine's form)."""
        return OffPolicyObjective(gamma=self.discount, actor_q="first", cost_reduction=self.cost_reduction,
                                  loss_function=self.loss_function, constrained=self.constrained,
                                  policy_noise=float(self.policy_noise), noise_clip=float(self.noise_clip))

    def _act(self, tensordict: TensorDictBase, params: TensorDictBase) -> Tensor:
        td = tensordict.select(*self.actor_network.in_keys, strict=False).copy()
        with params.to_module(self.actor_network):
            return self.actor_network(td).get(self.tensor_keys.action)

    def _next_action(self, tensordict):
        action = tensordict.get(self.tensor_keys.action)
        noise = torch.randn_like(action)  # drawn first, as TD3Loss draws it
        next_action = self._act(tensordict.get("next"), self.target_actor_network_params)
        objective = self.seed_batched_objective()
        return objective.smoothed_action(next_action, noise, self.min_action, self.max_action), None

    def _actor_action(self, tensordict):
        return self._act(tensordict, self.actor_network_params), None


class DDPGLagLoss(_CostCritic, DDPGLoss):
    """DDPG (``multiplier=None``), DDPG-Lag or DDPG-PID: TorchRL's ``DDPGLoss`` plus a cost critic.

    One reward critic and one cost critic (OmniSafe's), each with target parameters; the targets are taken at
    the target actor's action (``delay_actor=True``, the DDPG paper's target actor; TorchRL's default is the
    current actor).

    Args:
        actor_network, value_network: as ``DDPGLoss`` (``value_network`` is the Q(s, a) critic).
        cost_qvalue_network, multiplier, cost_reduction, loss_function: as :class:`SACLagLoss` (one cost critic:
            the reduction is the identity).
        **kwargs: ``DDPGLoss``'s other options.
    """

    @dataclass
    class _AcceptedKeys(DDPGLoss._AcceptedKeys):
        """``DDPGLoss``'s keys, ``cost``, and ``action`` (the actor's output and the critic's action input)."""

        cost: NestedKey = "cost"
        action: NestedKey = "action"

    default_keys = _AcceptedKeys

    def __init__(self, actor_network, value_network, cost_qvalue_network=None, multiplier: Multiplier | None = None,
                 *, cost_reduction: str = "max", loss_function: str = "l2", delay_actor: bool = True,
                 reduction: str | None = None, **kwargs) -> None:
        self._check_reduction(reduction)
        super().__init__(actor_network, value_network, loss_function=loss_function, delay_actor=delay_actor, **kwargs)
        self._init_constraint(cost_qvalue_network, multiplier, 1, cost_reduction)

    _critic_network = property(lambda self: self.value_network)
    _critic_params = property(lambda self: self.value_network_params)
    _target_critic_params = property(lambda self: self.target_value_network_params)

    def seed_batched_objective(self) -> OffPolicyObjective:
        """This loss's math for S stacked seeds (the engine's form)."""
        return OffPolicyObjective(gamma=self.discount, actor_q="first", cost_reduction=self.cost_reduction,
                                  loss_function=self.loss_function, constrained=self.constrained)

    def _act(self, tensordict: TensorDictBase, params: TensorDictBase) -> Tensor:
        td = tensordict.select(*self.actor_network.in_keys, strict=False).copy()
        with params.to_module(self.actor_network):
            return self.actor_network(td).get(self.tensor_keys.action)

    def _next_action(self, tensordict):
        params = self.target_actor_network_params if self.delay_actor else self.actor_network_params
        return self._act(tensordict.get("next"), params), None

    def _actor_action(self, tensordict):
        return self._act(tensordict, self.actor_network_params), None
