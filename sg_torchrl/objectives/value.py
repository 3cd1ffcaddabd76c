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
"""
from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.objectives.value import GAE

__all__ = ["make_gae", "make_cost_gae", "normalize_advantages"]


def make_gae(
    value_network: TensorDictModuleBase | None,
    *,
    gamma: float = 0.99,
    lmbda: float = 0.95,
    **gae_kwargs: Any,
) -> GAE:
    """Builds the reward GAE with TorchRL's default keys.

    Reads ``("next", "reward")``, ``("next", "done")``, ``("next", "terminated")`` and the
    critic's ``"state_value"``; writes ``"advantage"`` and ``"value_target"``.

    Args:
        value_network (TensorDictModuleBase or None): the reward critic, writing ``"state_value"``;
            ``None`` when the caller writes ``"state_value"`` and ``("next", "state_value")`` itself
            (e.g. in chunks, for image observations).

    Keyword Args:
        gamma (float): discount factor. Defaults to ``0.99`` (paper value).
        lmbda (float): GAE :math:`\\lambda`. Defaults to ``0.95`` (paper value).
        **gae_kwargs: forwarded to :class:`~torchrl.objectives.value.GAE` (e.g. ``time_dim``,
            ``vectorized``, ``device``).

    Returns:
        A :class:`~torchrl.objectives.value.GAE` module.
    """
    return GAE(gamma=gamma, lmbda=lmbda, value_network=value_network, **gae_kwargs)


def make_cost_gae(
    cost_value_network: TensorDictModuleBase | None,
    *,
    gamma: float = 0.99,
    lmbda: float = 0.95,
    **gae_kwargs: Any,
) -> GAE:
    """Builds the cost GAE: a :class:`~torchrl.objectives.value.GAE` over the cost signal.

    Configured with ``set_keys(reward="cost", value="cost_value", advantage="cost_advantage",
    value_target="cost_value_target")``: it reads ``("next", "cost")``, the done flags and the cost
    critic's ``"cost_value"``, and writes ``"cost_advantage"`` and ``"cost_value_target"``, so it
    runs on the same TensorDict as the reward GAE without touching its entries. Remap further with
    ``.set_keys(...)`` (e.g. multi-agent ``("agents", "cost")``).

    SafePO uses the same :math:`\\gamma` and :math:`\\lambda` for cost and reward
    (``lambda_c = 0.95``), which are the defaults here.

    Args:
        cost_value_network (TensorDictModuleBase or None): the cost critic, writing ``"cost_value"``;
            ``None`` when the caller writes ``"cost_value"`` and ``("next", "cost_value")`` itself.

    Keyword Args:
        gamma (float): cost discount factor. Defaults to ``0.99``.
        lmbda (float): GAE :math:`\\lambda` for the cost. Defaults to ``0.95``.
        **gae_kwargs: forwarded to :class:`~torchrl.objectives.value.GAE`.

    Returns:
        A :class:`~torchrl.objectives.value.GAE` module with the cost keys.
    """
    gae = GAE(gamma=gamma, lmbda=lmbda, value_network=cost_value_network, **gae_kwargs)
    gae.set_keys(
        reward="cost",
        value="cost_value",
        advantage="cost_advantage",
        value_target="cost_value_target",
    )
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
