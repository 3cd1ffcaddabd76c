"""Reward and cost advantage estimation (two GAEs side by side) and SafePO's batch normalisation.

Safe policy-gradient methods need two advantages per sample: :math:`A_r` from the reward critic
and :math:`A_c` from the cost critic. Both are Generalized Advantage Estimates (Schulman et al.
2016, https://arxiv.org/abs/1506.02438) with the same :math:`\\gamma` and :math:`\\lambda`
(0.99 / 0.95 in the Safety-Gymnasium paper); the cost one simply reads ``("next", "cost")`` and the
cost critic's ``"cost_value"`` instead of the reward and ``"state_value"``. Both are TorchRL's own
:class:`~torchrl.objectives.value.GAE`, so termination (no bootstrap), truncation (bootstrap from
the next-state value) and episode boundaries (``done`` cuts the recursion) are handled identically
for reward and cost.

Typical use, once per collected batch and before the minibatch loop::

    reward_gae = make_gae(critic)
    cost_gae = make_cost_gae(cost_critic)
    with torch.no_grad():
        reward_gae(batch)
        cost_gae(batch)
    normalize_advantages(batch)

Both factories place their keys beside the critic's output: a critic writing
``("agents", "cost_value")`` (a multi-agent group) gets ``("agents", "cost")``,
``("agents", "cost_advantage")``, ... and the group's done flags, TorchRL's multi-agent layout.

:class:`AdvantageEstimation` is the same computation inside a loss: TorchRL's convention that a
PPO-family loss computes the advantages its input lacks, here for the reward *and* the cost critic.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.objectives.utils import build_value_estimator, ValueEstimators
from torchrl.objectives.value import GAE, ValueEstimatorBase

__all__ = ["AdvantageEstimation", "make_gae", "make_cost_gae", "normalize_advantages"]


def _keys_beside(
    value_network: TensorDictModuleBase | None, names: Mapping[str, str], group: str | None = None
) -> dict[str, NestedKey]:
    """GAE keys for ``names`` (estimator key -> entry name), placed beside the critic's output.

    With ``group`` every key, the value's included, is ``(group, name)`` instead (the multi-agent
    factories name the group rather than reading it from the critic).

    The value key is the critic's out-key whose last element is ``names["value"]`` (or its only
    out-key); every other entry goes under the same prefix. A top-level critic therefore gets the
    plain names, and a critic writing ``("agents", "cost_value")`` gets ``("agents", "cost")``,
    ``("agents", "cost_advantage")``, ``("agents", "done")``, ...: TorchRL's multi-agent layout,
    where the per-agent signals and flags live in the group. TorchRL's ``GAE`` validates the value
    key against the critic's out-keys, so the plain default would fail for a nested critic.
    """
    if group is not None:
        return {name: unravel_key((group, entry)) for name, entry in names.items()}
    value: NestedKey = names["value"]
    out_keys = [unravel_key(key) for key in getattr(value_network, "out_keys", None) or []]
    if out_keys and value not in out_keys:
        nested = [key for key in out_keys if isinstance(key, tuple) and key[-1] == value]
        if len(nested) == 1:
            value = nested[0]
        elif len(out_keys) == 1:
            value = out_keys[0]
    prefix = value[:-1] if isinstance(value, tuple) else ()
    keys = {name: unravel_key((*prefix, entry)) for name, entry in names.items()}
    keys["value"] = value
    return keys


#: TorchRL's reward-GAE entries, and the cost GAE's: the same renamed for the cost signal and critic.
_REWARD_NAMES = {"reward": "reward", "value": "state_value", "advantage": "advantage",
                 "value_target": "value_target", "done": "done", "terminated": "terminated"}
_COST_NAMES = {**_REWARD_NAMES, "reward": "cost", "value": "cost_value", "advantage": "cost_advantage",
               "value_target": "cost_value_target"}


def make_gae(
    value_network: TensorDictModuleBase | None,
    *,
    gamma: float = 0.99,
    lmbda: float = 0.95,
    keys: Mapping[str, NestedKey] | None = None,
    group: str | None = None,
    estimator: type[GAE] = GAE,
    **gae_kwargs: Any,
) -> GAE:
    """Builds the reward GAE with TorchRL's default keys.

    Reads ``("next", "reward")``, ``("next", "done")``, ``("next", "terminated")`` and the
    critic's ``"state_value"``; writes ``"advantage"`` and ``"value_target"``. For a critic writing
    a nested key such as ``("agents", "state_value")`` all of these move into its group
    (``("agents", "reward")``, ``("agents", "done")``, ...).

    Args:
        value_network (TensorDictModuleBase or None): the reward critic, writing ``"state_value"``;
            ``None`` when the caller writes ``"state_value"`` and ``("next", "state_value")`` itself
            (e.g. in chunks, for image observations).

    Keyword Args:
        gamma (float): discount factor. Defaults to ``0.99`` (paper value).
        lmbda (float): GAE :math:`\\lambda`. Defaults to ``0.95`` (paper value).
        keys (mapping, optional): estimator keys to set instead of the defaults (``reward``,
            ``value``, ``advantage``, ``value_target``, ``done``, ``terminated``), applied in one
            ``set_keys`` call. Defaults to ``None``.
        group (str, optional): put every default key under ``group`` (``(group, "reward")``,
            ``(group, "state_value")``, ...) whatever the critic's out-key. Defaults to ``None``
            (beside the critic's output).
        estimator (type): the GAE class, e.g. :class:`~torchrl.objectives.value.MultiAgentGAE`
            (per-agent values over team-level signals, broadcast along the agent dim). Defaults
            to :class:`~torchrl.objectives.value.GAE`.
        **gae_kwargs: forwarded to ``estimator`` (e.g. ``time_dim``, ``vectorized``, ``device``,
            ``average_gae``).

    Returns:
        A :class:`~torchrl.objectives.value.GAE` module.
    """
    return _build(estimator, value_network, _REWARD_NAMES, gamma=gamma, lmbda=lmbda, keys=keys, group=group,
                  **gae_kwargs)


def make_cost_gae(
    cost_value_network: TensorDictModuleBase | None,
    *,
    gamma: float = 0.99,
    lmbda: float = 0.95,
    keys: Mapping[str, NestedKey] | None = None,
    group: str | None = None,
    estimator: type[GAE] = GAE,
    **gae_kwargs: Any,
) -> GAE:
    """Builds the cost GAE: a :class:`~torchrl.objectives.value.GAE` over the cost signal.

    Configured with ``set_keys(reward="cost", value="cost_value", advantage="cost_advantage",
    value_target="cost_value_target")``: it reads ``("next", "cost")``, the done flags and the cost
    critic's ``"cost_value"``, and writes ``"cost_advantage"`` and ``"cost_value_target"``, so it
    runs on the same TensorDict as the reward GAE without touching its entries. A nested cost critic
    (``("agents", "cost_value")``) gets every key in its group, one estimate per agent, as in
    :func:`make_gae`. SafePO uses the same :math:`\\gamma` and :math:`\\lambda` for cost and
    reward (``lambda_c = 0.95``), which are the defaults here.

    Args:
        cost_value_network (TensorDictModuleBase or None): the cost critic, writing ``"cost_value"``;
            ``None`` when the caller writes ``"cost_value"`` and ``("next", "cost_value")`` itself.

    Keyword Args:
        gamma, lmbda, keys, group, estimator, **gae_kwargs: as in :func:`make_gae` (``keys`` is applied
            in one ``set_keys`` call, so a nested value key never meets the plain default).

    Returns:
        A :class:`~torchrl.objectives.value.GAE` module with the cost keys.
    """
    return _build(estimator, cost_value_network, _COST_NAMES, gamma=gamma, lmbda=lmbda, keys=keys, group=group,
                  **gae_kwargs)


def _build(
    estimator: type[GAE],
    value_network: TensorDictModuleBase | None,
    names: Mapping[str, str],
    *,
    keys: Mapping[str, NestedKey] | None,
    group: str | None,
    **gae_kwargs: Any,
) -> GAE:
    """``estimator`` over ``value_network`` with the keys ``names`` placed (:func:`_keys_beside`), ``keys`` on top."""
    gae = estimator(value_network=value_network, **gae_kwargs)
    gae.set_keys(**{**_keys_beside(value_network, names, group), **(keys or {})})
    return gae


@torch.no_grad()
def normalize_advantages(
    td: TensorDictBase,
    *,
    reward_key: NestedKey | None = "advantage",
    cost_key: NestedKey | None = "cost_advantage",
    eps: float = 1e-8,
) -> TensorDictBase:
    """SafePO's batch-level advantage normalisation, in place.

    Over all elements of the batch (every env and time step):

    * the reward advantage is standardised, :math:`(A_r - \\mathrm{mean}) / (\\mathrm{std} + \\epsilon)`
      with the unbiased (Bessel-corrected) standard deviation, as ``torch.std`` computes it in
      SafePO's buffer;
    * the cost advantage is **only mean-centred**, :math:`A_c - \\mathrm{mean}`, not divided by its
      standard deviation. This is what SafePO's single-agent buffer does (its multi-agent code
      standardises both); keeping the cost scale makes :math:`\\lambda A_c` commensurate with the
      multiplier learned from raw episode costs.

    Call it once on the whole epoch's batch, after both GAEs and before splitting into
    minibatches: the loss does no advantage normalisation of its own.

    Args:
        td (TensorDictBase): the batch holding the advantages. Modified in place and returned.

    Keyword Args:
        reward_key (NestedKey, optional): reward-advantage entry; ``None`` skips it. Defaults to
            ``"advantage"``.
        cost_key (NestedKey, optional): cost-advantage entry; ``None`` skips it. Defaults to
            ``"cost_advantage"``.
        eps (float): added to the standard deviation. Defaults to ``1e-8`` (SafePO).

    Returns:
        ``td``, with the normalised entries.

    Raises:
        KeyError: if a requested key is missing.
    """
    if reward_key is not None:
        adv = _get_required(td, reward_key)
        td.set(reward_key, (adv - adv.mean()) / (adv.std() + eps))
    if cost_key is not None:
        cadv = _get_required(td, cost_key)
        td.set(cost_key, cadv - cadv.mean())
    return td


def _get_required(td: TensorDictBase, key: NestedKey) -> torch.Tensor:
    # tensordict 0.14's ``get`` returns None for a missing key instead of raising.
    value = td.get(key, None)
    if value is None:
        raise KeyError(f"normalize_advantages: {key!r} is not in the batch (run the GAE first).")
    return value


class AdvantageEstimation:
    """TorchRL's "a loss computes the advantages it is not given", for a reward and a cost critic.

    TorchRL's :class:`~torchrl.objectives.ClipPPOLoss` runs its value estimator when its input has
    no advantage, so a raw rollout can go straight into the loss. A safe loss needs two advantages;
    this mixin, placed before :class:`~torchrl.objectives.ClipPPOLoss` in
    :class:`~sg_torchrl.objectives.PPOLagLoss` (and so in every first-order safe loss), adds

    * :attr:`cost_value_estimator`, the cost critic's estimator beside TorchRL's
      :attr:`value_estimator`: same type and hyper-parameters (``make_value_estimator`` builds
      both; GAE with :math:`\\gamma = 0.99`, :math:`\\lambda = 0.95` by default, the paper's), the
      loss's cost keys (``set_keys`` reaches it);
    * :meth:`estimate_advantages`, both advantages and value targets of a whole batch followed by
      :func:`normalize_advantages`, SafePO's batch rule (reward standardised, cost only centred,
      over every element): exactly what the trainer computes before its minibatch loop;
    * :meth:`set_group`, every key moved into a multi-agent env's group (``("agents", ...)``) in one call;
    * :meth:`_with_advantages`, which the loss's ``forward`` calls: a batch holding both
      advantages (the trainer's minibatches) is used as given; otherwise the missing ones are
      computed on a shallow copy (the caller's TensorDict is not written to).

    The estimate needs whole trajectories (``("next", "reward")``, ``("next", "cost")``, the done
    flags, time as the last batch dim): feed the loss a rollout, or compute the advantages once
    per batch with :meth:`estimate_advantages` before splitting it into minibatches.

    The host class provides the cost keys in ``tensor_keys`` (``cost``, ``cost_value``,
    ``cost_advantage``, ``cost_value_target``) and the cost critic as ``cost_critic_network``
    (with ``cost_critic_network_params`` / ``target_cost_critic_network_params`` when functional).
    """

    #: Whether ``forward`` computes missing advantages. Off for losses fed flattened per-agent
    #: views (:class:`~sg_torchrl.objectives.multi_agent.AgentPPOLoss`): no time axis is left there.
    _estimates_missing_advantages: bool = True

    @property
    def cost_value_estimator(self) -> ValueEstimatorBase:
        """The cost critic's value estimator (built with the reward one on first use).

        Read-only: configure it with :meth:`make_value_estimator` (an ``nn.Module`` assigned to an
        attribute of a module bypasses property setters, TorchRL's ``value_estimator`` included).
        """
        if getattr(self, "_cost_value_estimator", None) is None:
            reward_estimator = self.value_estimator  # first use builds both (make_value_estimator)
            if getattr(self, "_cost_value_estimator", None) is None:  # an instance was given
                discounts = {name: float(getattr(reward_estimator, name))
                             for name in ("gamma", "lmbda") if hasattr(reward_estimator, name)}
                self._cost_value_estimator = self.make_cost_value_estimator(**discounts)
        return self._cost_value_estimator

    def make_value_estimator(self, value_type: ValueEstimators | None = None, **hyperparams: Any):
        """TorchRL's ``make_value_estimator`` for the reward critic, and the same for the cost critic.

        ``loss.make_value_estimator(ValueEstimators.GAE, gamma=0.99, lmbda=0.97)`` configures both
        estimators alike. Given an estimator instance or class (TorchRL's other form), only the
        reward one is replaced and the cost one becomes a GAE with its ``gamma`` / ``lmbda``.
        """
        super().make_value_estimator(value_type, **hyperparams)
        self._cost_value_estimator = None
        if value_type is None:
            value_type = self.default_value_estimator
        if isinstance(value_type, ValueEstimatorBase) or isinstance(value_type, type):
            return self
        # TorchRL's convention (dispatch_value_estimator): a loss's own ``gamma`` is the default discount.
        if hasattr(self, "gamma"):
            hyperparams.setdefault("gamma", self.gamma)
        estimator = build_value_estimator(self, value_type, **hyperparams, value_network=self.cost_critic_network)
        estimator.set_keys(**self._cost_estimator_keys())
        self._cost_value_estimator = estimator
        return self

    def make_cost_value_estimator(
        self, *, gamma: float = 0.99, lmbda: float = 0.95, **gae_kwargs: Any
    ) -> GAE:
        """A cost GAE over this loss's cost critic and keys (``tensor_keys.cost``, ``cost_value``, ...).

        Convenience for :func:`make_cost_gae` that follows any :meth:`set_keys` remapping (cost,
        cost value, cost advantage / target, done, terminated; nested keys included). The estimator
        is returned, not stored (:attr:`cost_value_estimator` is the loss's own): run it on the
        whole batch before the minibatch loop.

        Keyword Args:
            gamma (float): discount. Defaults to ``0.99``.
            lmbda (float): GAE lambda. Defaults to ``0.95``.
            **gae_kwargs: forwarded to :class:`~torchrl.objectives.value.GAE`.
        """
        return make_cost_gae(self.cost_critic_network, gamma=gamma, lmbda=lmbda,
                             keys=self._cost_estimator_keys(), **gae_kwargs)

    def set_group(self, group: str) -> AdvantageEstimation:
        """Point every tensordict key of the loss at the entries of the agent group ``group``; returns ``self``.

        A multi-agent env (e.g. ``sg_torchrl.make("Safety2x3HalfCheetahVelocity-v0")``) keeps its
        per-agent entries in a group: ``("agents", "action")``, ``("next", "agents", "reward")``,
        ``("next", "agents", "cost")``, ... . ``loss.set_group("agents")`` is the one call that
        remaps the loss (and its reward and cost estimators) onto them: each key of
        :attr:`tensor_keys` (action, log-prob, advantages, value targets, values, reward, cost,
        done, terminated, and a subclass's own such as ``factor``) becomes ``(group, key)``, unless it
        already lies in the group; the log-prob key is left unset (``None``) if it is, as it then
        follows the actor. The networks' own ``in_keys`` / ``out_keys`` are the networks' business:
        give them the group's keys (``("agents", "observation")`` -> ``("agents", "state_value")``).
        Equivalent to ``loss.set_keys(action=("agents", "action"), ...)`` over every key.

        Raises:
            ValueError: ``group`` is not a non-empty string.
        """
        if not isinstance(group, str) or not group:
            raise ValueError(f"group must be the name of an agent group (e.g. 'agents'), got {group!r}")
        keys = {}
        for name in self._AcceptedKeys.__dataclass_fields__:
            key = getattr(self.tensor_keys, name)
            if key is None:
                continue
            path = (key,) if isinstance(key, str) else tuple(key)
            if path[0] != group:
                keys[name] = (group, *path)
        self.set_keys(**keys)
        return self

    def _cost_estimator_keys(self) -> dict[str, NestedKey]:
        tk = self.tensor_keys
        return {"reward": tk.cost, "value": tk.cost_value, "advantage": tk.cost_advantage,
                "value_target": tk.cost_value_target, "done": tk.done, "terminated": tk.terminated}

    def _forward_value_estimator_keys(self, **kwargs: Any) -> None:
        estimator = getattr(self, "_cost_value_estimator", None)
        if estimator is not None:
            estimator.set_keys(**self._cost_estimator_keys())
        super()._forward_value_estimator_keys(**kwargs)

    def estimate_advantages(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Reward and cost advantages and value targets of a whole batch, in place, SafePO-normalised.

        Runs :attr:`value_estimator` (reward critic) and :attr:`cost_value_estimator` (cost critic)
        without gradients, then :func:`normalize_advantages`; overwrites existing entries. This is
        the trainer's per-batch computation, for loops that split the batch into minibatches.

        Returns:
            ``tensordict``, holding ``advantage``, ``value_target``, ``cost_advantage`` and
            ``cost_value_target`` (under the loss's keys) and the critics' values.

        Raises:
            KeyError: if the reward or cost signal (under ``"next"``) is missing.
        """
        self._estimate(tensordict, reward=True, cost=True)
        return tensordict

    def _with_advantages(
        self, tensordict: TensorDictBase, *, reward: bool = True, cost: bool = True
    ) -> TensorDictBase:
        """``tensordict`` if it holds the advantages asked for, else a shallow copy with the missing ones."""
        if not self._estimates_missing_advantages:
            return tensordict
        tk = self.tensor_keys
        reward = reward and tensordict.get(tk.advantage, None) is None
        cost = cost and tensordict.get(tk.cost_advantage, None) is None
        if not (reward or cost):
            return tensordict
        tensordict = tensordict.clone(False)
        self._estimate(tensordict, reward=reward, cost=cost)
        return tensordict

    @torch.no_grad()
    def _estimate(self, tensordict: TensorDictBase, *, reward: bool, cost: bool) -> None:
        tk = self.tensor_keys
        jobs = []
        if reward:
            params = self.critic_network_params.detach() if self.functional else None
            jobs.append((self.value_estimator, tk.advantage, params, self.target_critic_network_params))
        if cost:
            params = self.cost_critic_network_params.detach() if self.functional else None
            jobs.append((self.cost_value_estimator, tk.cost_advantage,
                         params, self.target_cost_critic_network_params))
        for estimator, advantage_key, _, _ in jobs:  # check all first: no half-written batch
            signal = unravel_key(("next", estimator.tensor_keys.reward))
            if tensordict.get(signal, None) is None:
                raise KeyError(
                    f"{type(self).__name__} did not find {advantage_key!r} in the input and cannot "
                    f"compute it: {signal!r} is missing. It estimates advantages from whole "
                    f"trajectories (a rollout); otherwise compute them on the whole batch first "
                    f"(loss.estimate_advantages, or make_gae / make_cost_gae and "
                    f"normalize_advantages), or remap the keys with loss.set_keys(...)."
                )
        for estimator, _, params, target_params in jobs:
            estimator(tensordict, params=params, target_params=target_params)
        normalize_advantages(
            tensordict,
            reward_key=tk.advantage if reward else None,
            cost_key=tk.cost_advantage if cost else None,
        )
