"""A loaded policy's modules: its network on plain tensors and the TorchRL policy around it.

A network maps the raw observation tensors (``in_keys`` order, any leading batch dims) to actions, the frozen
observation normaliser folded in, with two methods: ``mean_action(*inputs)`` (what training's evaluation
acts with, and what :func:`~sg_torchrl.evaluation.export.export_policy` exports) and
``sample_action(*inputs)`` (``stochastic`` networks only). One per kind of actor:

* :class:`PolicyNetwork`: a Gaussian head, ``(loc, scale)`` (the on-policy actors, one agent's or a team's
  per-agent heads); its mean action is ``loc``;
* :class:`OffPolicyActorNetwork`: the off-policy actors, SAC's tanh-squashed Gaussian (its mean action
  the squashed ``loc``, ``TanhNormal``'s deterministic sample) or TD3's / DDPG's deterministic tanh actor.

:class:`TrainedPolicy` is the ``TensorDictModule`` a loader (:mod:`sg_torchrl.evaluation.loaders`) returns.
Every formula here is the training module's, in the same operations and order, so the actions are its
bits (``tests/test_evaluation.py``, ``tests/test_evaluation_families.py``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.data import TensorSpec
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import IndependentNormal, TanhNormal

from sg_torchrl.envs.normalization import standardize
from sg_torchrl.modules.mlp import ObservationLayout
from sg_torchrl.train.config import TrainConfig

__all__ = ["ObservationScaler", "OffPolicyActorNetwork", "PolicyNetwork", "TrainedPolicy", "input_dtype", "key_name"]

_DETERMINISTIC = (None, ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN)


def input_dtype(key: NestedKey) -> torch.dtype:
    """The dtype a policy reads ``key`` in: ``uint8`` camera pixels, else ``float32``."""
    return torch.uint8 if key == "pixels" else torch.float32


def key_name(key: NestedKey) -> str:
    """``key`` as one string (``("agents", "observation")`` -> ``"agents/observation"``), for files and messages."""
    return key if isinstance(key, str) else "/".join(key)


class ObservationScaler(nn.Module):
    """A frozen :class:`~sg_torchrl.envs.normalization.RunningObservationNorm` (one set of statistics, any
    feature shape: ``(obs_dim,)`` or a team's ``(n_agents, obs_dim)``) as a tensor module:
    :func:`~sg_torchrl.envs.normalization.standardize`, back in ``x``'s dtype, as the transform computes it
    (the same operations in the same order, so the same bits)."""

    def __init__(self, mean: Tensor, var: Tensor, epsilon: float = 1e-8) -> None:
        super().__init__()
        self.register_buffer("mean", mean.detach().to(torch.float64).clone())
        self.register_buffer("var", var.detach().to(torch.float64).clone())
        self.epsilon = float(epsilon)

    def forward(self, x: Tensor) -> Tensor:
        return standardize(x, self.mean, self.var, self.epsilon).to(x.dtype)


class _ScaledInputs(nn.Module):
    """Inputs in ``in_keys`` order with the normaliser applied to the entry ``normalized_key`` (if any)."""

    def __init__(self, in_keys: Sequence[NestedKey], scaler: ObservationScaler | None,
                 normalized_key: NestedKey = "observation") -> None:
        super().__init__()
        self.in_keys = list(in_keys)
        self.scaler = scaler
        self._normalized = self.in_keys.index(normalized_key) if normalized_key in self.in_keys else -1

    def scaled(self, inputs: Sequence[Tensor]) -> tuple[Tensor, ...]:
        if self.scaler is None or self._normalized < 0:
            return tuple(inputs)
        return tuple(self.scaler(x) if i == self._normalized else x for i, x in enumerate(inputs))


class PolicyNetwork(_ScaledInputs):
    """A Gaussian head with the observation normaliser folded in: raw inputs -> ``(loc, scale)``.

    ``head(*inputs) -> (loc, scale)``: a single-agent actor's network (``in_keys``: ``pixels``, ``depth``,
    ``observation``, those the run reads; images are scaled inside it, as in training), or a team's
    per-agent policy (``("agents", "observation")`` ``(*B, A, D)`` -> ``(*B, A, Da)``). Only
    ``normalized_key`` is normalised.
    """

    stochastic = True

    def __init__(self, head: nn.Module, in_keys: Sequence[NestedKey], scaler: ObservationScaler | None,
                 normalized_key: NestedKey = "observation") -> None:
        super().__init__(in_keys, scaler, normalized_key)
        self.head = head

    def forward(self, *inputs: Tensor) -> tuple[Tensor, Tensor]:
        loc, scale = self.head(*self.scaled(inputs))
        return loc, scale.expand_as(loc)

    def mean_action(self, *inputs: Tensor) -> Tensor:
        return self(*inputs)[0]

    def sample_action(self, *inputs: Tensor) -> Tensor:
        """A sample of the Gaussian (global torch RNG), as the training actor's ``IndependentNormal``."""
        return IndependentNormal(*self(*inputs)).sample()


class OffPolicyActorNetwork(_ScaledInputs):
    """An off-policy actor (:func:`~sg_torchrl.modules.off_policy.make_off_policy_networks`'s) on plain tensors.

    Built by :meth:`from_actor` from the TorchRL actor itself (its network, bounds and squashing options).
    The mean action is what that actor returns under a deterministic exploration type, in its operations:

    * SAC (``TanhNormal``'s deterministic sample): ``tanh(loc)`` clamped to ``±(1 - resolution)`` (TorchRL's
      safe tanh), then ``(high + low) / 2 + (high - low) / 2 * y`` when the bounds are not [-1, 1];
    * TD3 / DDPG (``TanhModule``): ``tanh(x)`` (clamped if the module clamps), then ``low + (high - low) *
      (y + 1) / 2`` when the module rescales (TorchRL's ``TanhModule`` does so whenever it records its bounds'
      triviality, i.e. always, [-1, 1] bounds included: a no-op up to float rounding, kept for the same bits).

    ``sample_action``: SAC's ``TanhNormal`` sample; TD3 and DDPG have none (their exploration noise is a
    training device, not part of the policy).
    """

    def __init__(self, body: nn.Module, low: Tensor, high: Tensor, *, stochastic: bool, rescale: bool,
                 clamp: bool) -> None:
        super().__init__(["observation"], None)
        self.body, self.stochastic, self.rescale, self.clamp = body, bool(stochastic), bool(rescale), bool(clamp)
        self.register_buffer("low", low.detach().clone())
        self.register_buffer("high", high.detach().clone())

    @classmethod
    def from_actor(cls, actor: nn.Module, *, stochastic: bool) -> OffPolicyActorNetwork:
        """The network of a :func:`~sg_torchrl.modules.off_policy.make_off_policy_networks` actor (sharing its
        parameters): SAC's ``ProbabilisticActor`` (network, ``TanhNormal`` bounds) or TD3's / DDPG's
        ``TensorDictSequential`` (network, ``TanhModule``)."""
        body, squash = actor.module[0].module, actor.module[1]
        if stochastic:
            low, high = squash.distribution_kwargs["low"], squash.distribution_kwargs["high"]
            return cls(body, low, high, stochastic=True, rescale=bool((low != -1).any() or (high != 1).any()),
                       clamp=True)
        key = squash.out_keys[0]
        name = key if isinstance(key, str) else "_".join(key)
        return cls(body, getattr(squash, f"{name}_low"), getattr(squash, f"{name}_high"), stochastic=False,
                   rescale=bool(squash.non_trivial), clamp=squash.clamp)

    def mean_action(self, observation: Tensor) -> Tensor:
        low, high = self.low, self.high
        if self.stochastic:
            loc = self.body(observation)[0]
            limit = 1.0 - torch.finfo(loc.dtype).resolution
            action = loc.tanh().clamp(-limit, limit)
            return (high + low) / 2 + (high - low) / 2 * action if self.rescale else action
        action = self.body(observation).tanh()
        if self.clamp:
            eps = torch.finfo(action.dtype).resolution
            action = action.clamp(-1 + eps, 1 - eps)
        return low + (high - low) * (action + 1) / 2 if self.rescale else action

    def forward(self, observation: Tensor) -> Tensor:
        return self.mean_action(observation)

    def sample_action(self, observation: Tensor) -> Tensor:
        if not self.stochastic:
            raise ValueError("this actor is deterministic (TD3, DDPG): it has no action distribution to sample")
        loc, scale = self.body(observation)
        return TanhNormal(loc, scale, low=self.low, high=self.high).sample()


class TrainedPolicy(TensorDictModuleBase):
    """One seed's trained actor with its frozen observation normaliser folded in (a TorchRL policy).

    Reads :attr:`in_keys` (the raw env entries: ``"observation"``, ``"pixels"`` / ``"depth"`` for pixel runs,
    ``("agents", "observation")`` for a team) and writes :attr:`out_keys` (``"action"``, a team's
    ``("agents", "action")``): the mean action by default and under a deterministic exploration type, a
    sample (global torch RNG) under ``ExplorationType.RANDOM`` when the actor has a distribution
    (:attr:`stochastic`; TD3's and DDPG's act deterministically whatever the exploration type).

    Attributes:
        network: raw tensors -> actions (:class:`PolicyNetwork`, :class:`OffPolicyActorNetwork`).
        config: the seed's single-seed :class:`~sg_torchrl.train.config.TrainConfig` (env id, options).
        seed: the run seed the policy was trained with.
        input_shapes: each in-key's shape without the batch dims (a team's ``(n_agents, obs_dim)``).
        layout: what a single-agent policy reads (:class:`~sg_torchrl.modules.mlp.ObservationLayout`);
            ``None`` for a team.
        action_spec: the env's action spec (one simulator's; a team's ``(n_agents, max action size)``).
        epoch: the training epoch of the checkpoint.
        diverged: ``None``, or the seed's divergence record (its weights are those before it diverged).
    """

    def __init__(self, network: nn.Module, *, in_keys: Sequence[NestedKey], out_key: NestedKey,
                 input_shapes: Mapping[NestedKey, tuple[int, ...]], action_spec: TensorSpec, config: TrainConfig,
                 seed: int, epoch: int, layout: ObservationLayout | None = None,
                 diverged: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.network = network
        self.in_keys, self.out_keys = list(in_keys), [out_key]
        self.input_shapes = {key: tuple(shape) for key, shape in input_shapes.items()}
        self.config, self.seed, self.layout, self.action_spec = config, seed, layout, action_spec
        self.epoch, self.diverged = epoch, diverged

    @property
    def device(self) -> torch.device:
        return next(self.network.parameters()).device

    @property
    def stochastic(self) -> bool:
        """Whether the actor has an action distribution to sample (not TD3's or DDPG's)."""
        return self.network.stochastic

    @property
    def action_shape(self) -> tuple[int, ...]:
        """One action's shape (``(action_dim,)``, a team's ``(n_agents, max action size)``)."""
        return tuple(self.action_spec.shape)

    def _actions(self, inputs: list[Tensor], deterministic: bool | None = None) -> Tensor:
        if deterministic is None:
            deterministic = exploration_type() in _DETERMINISTIC or not self.stochastic
        return self.network.mean_action(*inputs) if deterministic else self.network.sample_action(*inputs)

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        inputs = [tensordict.get(key) for key in self.in_keys]
        device = inputs[0].device
        action = self._actions([x.to(self.device) for x in inputs])
        tensordict.set(self.out_keys[0], action.to(device))
        return tensordict

    @torch.no_grad()
    def act(self, observation: np.ndarray | Mapping[NestedKey, np.ndarray], deterministic: bool = True) -> np.ndarray:
        """Actions for numpy observations, one or a batch: ``(obs_dim,)`` -> ``(action_dim,)``, ``(B, obs_dim)`` ->
        ``(B, action_dim)``; a team's ``(A, obs_dim)`` -> ``(A, Da)``, ``(B, A, obs_dim)`` -> ``(B, A, Da)``.

        ``observation``: the raw array as the env emits it, or for a pixel run a mapping of :attr:`in_keys` to
        arrays (``"pixels"`` ``(H, W, 3)`` ``uint8`` ...). ``deterministic``: the mean action (default), else a
        sample (global torch RNG; not for TD3 and DDPG). Returns ``float32``.
        """
        if not deterministic and not self.stochastic:
            raise ValueError(f"a {self.config.algo} actor is deterministic: act(deterministic=False) has nothing "
                             f"to sample")
        if not isinstance(observation, Mapping):
            if len(self.in_keys) != 1:
                raise ValueError(f"this policy reads {self.in_keys}: give a mapping of those keys to arrays")
            observation = {self.in_keys[0]: observation}
        missing = [key for key in self.in_keys if key not in observation]
        if missing:
            raise ValueError(f"observation lacks {missing} (this policy reads {self.in_keys})")
        inputs, single = [], None
        for key in self.in_keys:
            array = np.asarray(observation[key])
            trailing = self.input_shapes[key]
            if array.shape[-len(trailing):] != trailing or array.ndim not in (len(trailing), len(trailing) + 1):
                raise ValueError(f"{key_name(key)!r} has shape {array.shape}; this policy takes {trailing} or "
                                 f"(B, *{trailing})")
            single = array.ndim == len(trailing) if single is None else single
            tensor = torch.as_tensor(array, dtype=input_dtype(key), device=self.device)
            inputs.append(tensor.unsqueeze(0) if array.ndim == len(trailing) else tensor)
        action = self._actions(inputs, deterministic).cpu().numpy()
        return action[0] if single else action
