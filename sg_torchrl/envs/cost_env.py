"""Any env plus a cost function: a TorchRL env with ``cost`` and ``cost_info``, trainable by ``sg-train``'s engine.

A safe env in sg_torchrl emits ``cost`` ``(N, 1)`` (same dtype as ``reward``) and one ``("cost_info",
name)`` entry per constraint beside the observation (:mod:`sg_torchrl.envs.base` says why costs live in
the observation spec). :func:`make_cost_env` gives any gymnasium env id, or a factory of gymnasium or
TorchRL envs, that layout: TorchRL wraps the env (``GymEnv``), ``SerialEnv`` batches ``num_envs`` copies
and :class:`CostTransform` adds the cost computed by the user's ``cost_fn``. Nothing of gymnasium's
wrapping is rewritten here.

``cost_fn(obs, action, next_obs, info)`` is called once per step for the whole batch: ``obs`` /
``next_obs`` the ``(N, ...)`` observations before and after the step, ``action`` ``(N, ...)``, ``info`` a
dict of the ``info_keys`` read from the step's output (entries the wrapped env emits, e.g. through
``GymEnv``'s ``info`` reader); it returns a tensor of shape ``(N,)`` or ``(N, 1)`` (or anything
``torch.as_tensor`` turns into one), or a Python number, the same cost for every simulator.

Seeding follows :class:`~sg_torchrl.envs.base.SafeEnv`'s rule (:func:`sg_torchrl.seeding.block_seeds`):
simulator ``i`` of an env seeded ``s`` is seeded from ``(s, i)`` alone, and a list of seeds seeds blocks,
so ``sg-train``'s seed groups work. Register one as an id with
:func:`sg_torchrl.tasks.register_cost_env`; then ``sg_torchrl.make(id, num_envs=N)`` and ``sg-train
--env-id id`` (in-process) build it like any other id.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import gymnasium
import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import EnvBase, GymEnv, SerialEnv, Transform, TransformedEnv
from torchrl.envs.libs.gym import GymWrapper

from sg_torchrl.seeding import block_seeds

__all__ = ["CostFunction", "CostTransform", "make_cost_env"]

#: ``cost_fn(obs, action, next_obs, info) -> float | tensor`` (module docstring)
CostFunction = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]], Any]


class CostTransform(Transform):
    """Adds ``cost`` and ``("cost_info", name)`` computed by ``cost_fn`` after every step (zeros after a reset).

    Args:
        cost_fn: the cost of a step (module docstring).
        name: the constraint's name, its ``cost_info`` entry.
        info_keys: entries of the step's output handed to ``cost_fn`` as ``info``.
        observation_key: where the observation is.
    """

    def __init__(self, cost_fn: CostFunction, name: str = "cost", info_keys: Sequence[str] = (),
                 observation_key: str = "observation") -> None:
        if not callable(cost_fn):
            raise TypeError(f"cost_fn must be callable, got {cost_fn!r}")
        super().__init__(in_keys=[], out_keys=["cost", ("cost_info", name)])
        self.cost_fn = cost_fn
        self.name = name
        self.info_keys = tuple(info_keys)
        self.observation_key = observation_key

    def _cost_shape(self) -> torch.Size:
        return torch.Size((*self.parent.batch_size, 1))

    def _dtype(self) -> torch.dtype:
        return self.parent.full_reward_spec[self.parent.reward_key].dtype

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        missing = [key for key in self.info_keys if key not in next_tensordict.keys()]
        if missing:
            raise KeyError(f"CostTransform: info_keys {missing} are not in the step's output "
                           f"(it has {sorted(map(str, next_tensordict.keys()))})")
        info = {key: next_tensordict.get(key) for key in self.info_keys}
        value = self.cost_fn(tensordict.get(self.observation_key), tensordict.get("action"),
                             next_tensordict.get(self.observation_key), info)
        shape, dtype = self._cost_shape(), self._dtype()
        cost = torch.as_tensor(value, dtype=dtype, device=next_tensordict.device)
        try:
            cost = cost.expand(shape) if cost.numel() == 1 else cost.reshape(shape)
        except RuntimeError:
            raise ValueError(f"cost_fn returned shape {tuple(cost.shape)}; expected one value per simulator, "
                             f"{tuple(shape[:-1])} or {tuple(shape)}, or a number") from None
        if not torch.isfinite(cost).all():
            raise ValueError(f"cost_fn returned a non-finite cost: {cost.flatten().tolist()}")
        next_tensordict.set("cost", cost.clone())
        next_tensordict.set(("cost_info", self.name), cost.clone())
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        zeros = torch.zeros(self._cost_shape(), dtype=self._dtype(), device=tensordict_reset.device)
        tensordict_reset.set("cost", zeros)
        tensordict_reset.set(("cost_info", self.name), zeros.clone())
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape, dtype = self._cost_shape(), self._dtype()
        device = observation_spec.device
        observation_spec["cost"] = Unbounded(shape=shape, dtype=dtype, device=device)
        observation_spec["cost_info"] = Composite(
            {self.name: Unbounded(shape=shape, dtype=dtype, device=device)}, shape=shape[:-1], device=device)
        return observation_spec


def _one_env(env: str | Callable[[], Any], max_episode_steps: int | None, device: Any) -> EnvBase:
    """One TorchRL env: a gymnasium id through ``GymEnv``, or what a factory returns (a gymnasium env wrapped)."""
    if isinstance(env, str):
        options = {} if max_episode_steps is None else {"max_episode_steps": max_episode_steps}
        return GymEnv(env, device=device, **options)
    built = env()
    if isinstance(built, EnvBase):
        return built
    return GymWrapper(built, device=device)


def make_cost_env(
    env: str | Callable[[], Any],
    cost_fn: CostFunction,
    *,
    num_envs: int = 1,
    device: torch.device | str = "cpu",
    seed: int | list[int] | None = None,
    max_episode_steps: int | None = None,
    cost_name: str = "cost",
    info_keys: Sequence[str] = (),
) -> TransformedEnv:
    """``num_envs`` copies of ``env`` with the cost ``cost_fn`` (module docstring), ``batch_size=[num_envs]``.

    Args:
        env: a gymnasium id (``"Pendulum-v1"``), or a factory returning a fresh gymnasium env or TorchRL env.
        cost_fn: ``cost_fn(obs, action, next_obs, info)``, the cost of a step for the whole batch.
        num_envs, device, seed: as :func:`sg_torchrl.make` (a list of seeds seeds blocks of simulators).
        max_episode_steps: the episode length: gymnasium's time limit for an id (``None``: the id's own);
            a factory's env keeps its own (the value only bounds evaluation rollouts; ``None``: 1000).
        cost_name: the constraint's ``cost_info`` entry.
        info_keys: entries of the step's output passed to ``cost_fn`` as ``info``.

    The returned env has ``max_episode_steps`` (the wrapped env's limit, for evaluation rollouts).
    """
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
    if not (isinstance(env, str) or callable(env)):
        raise TypeError(f"env must be a gymnasium id or a factory of envs, got {env!r}")
    seeds = [int(sequence.generate_state(1)[0]) for sequence in block_seeds(seed, num_envs)]

    def factory(index: int) -> Callable[[], EnvBase]:
        def build() -> EnvBase:
            one = _one_env(env, max_episode_steps, device)
            one.set_seed(seeds[index])
            return one
        return build

    batched = SerialEnv(num_envs, [factory(i) for i in range(num_envs)], device=device)
    batched.start()  # built now: a failing env fails here, and attribute lookups need the started workers
    cost_env = TransformedEnv(batched, CostTransform(cost_fn, cost_name, info_keys))
    if max_episode_steps is None:  # the id's own limit; a factory's env: evaluation rollouts of 1000 steps
        max_episode_steps = (gymnasium.spec(env).max_episode_steps if isinstance(env, str) else None) or 1000
    cost_env.max_episode_steps = int(max_episode_steps)
    return cost_env
