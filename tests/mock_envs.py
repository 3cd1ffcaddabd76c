"""Small deterministic batched envs that follow sg_torchrl's data convention.

``CountingCostEnv`` is a TorchRL ``EnvBase`` with ``batch_size=[N]`` whose episode statistics can
be computed by hand, so tests of episode accounting (transforms, collector statistics) can compare
against exact numbers:

* sub-env ``i`` ends its episode after ``base_length + i`` steps (``terminated`` for even ``i``,
  ``truncated`` for odd ``i``), so episode lengths differ per env and episodes end out of phase;
* ``reward`` is 1 on every step, so an episode's return equals its length ``L``;
* ``("cost_info", "odd")`` is 1 on the 1st, 3rd, 5th, ... step of an episode -> ``ceil(L/2)``;
  ``("cost_info", "third")`` is 1 on the 3rd, 6th, ... step                    -> ``L // 3``;
  ``cost`` is their sum (as Safety-Gymnasium sums its ``cost_*`` terms) -> ``ceil(L/2) + L//3``.

As in every sg_torchrl env, ``cost`` and ``cost_info`` are declared in the observation spec with
the reward's shape and dtype, leaving ``reward`` the only reward key.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase


def expected_episode(length: int) -> dict[str, float]:
    """Hand-computed statistics of one ``CountingCostEnv`` episode of ``length`` steps."""
    odd = (length + 1) // 2
    third = length // 3
    return {
        "return": float(length),
        "cost": float(odd + third),
        "length": length,
        "cost_info/odd": float(odd),
        "cost_info/third": float(third),
    }


def expected_step_costs(length: int) -> list[float]:
    """Per-step cost of one episode of ``length`` steps (step index starts at 1)."""
    return [float(t % 2 == 1) + float(t % 3 == 0) for t in range(1, length + 1)]


class CountingCostEnv(EnvBase):
    """``N`` deterministic sub-envs with per-env episode lengths ``base_length + i``."""

    _batch_locked = True

    def __init__(self, num_envs: int = 4, base_length: int = 3, obs_dim: int = 2):
        super().__init__(device="cpu", batch_size=torch.Size([num_envs]))
        n = num_envs
        self.num_envs = num_envs
        self.lengths = torch.arange(n, dtype=torch.int64) + base_length
        self._t = torch.zeros(n, dtype=torch.int64)
        self.obs_dim = obs_dim

        def scalar():
            return Unbounded(shape=(n, 1), dtype=torch.float32)

        self.observation_spec = Composite(
            observation=Unbounded(shape=(n, obs_dim), dtype=torch.float32),
            cost=scalar(),
            cost_info=Composite(odd=scalar(), third=scalar(), shape=(n,)),
            shape=(n,),
        )
        self.action_spec = Bounded(low=-1.0, high=1.0, shape=(n, 1), dtype=torch.float32)
        self.reward_spec = scalar()

        def flag():
            return Categorical(2, shape=(n, 1), dtype=torch.bool)

        self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=(n,))

    def _observation(self) -> torch.Tensor:
        obs = torch.zeros(self.num_envs, self.obs_dim)
        obs[:, 0] = self._t.float()
        obs[:, 1:] = torch.arange(self.num_envs, dtype=torch.float32).unsqueeze(-1)
        return obs

    def _costs(self) -> tuple[torch.Tensor, torch.Tensor]:
        t = self._t.unsqueeze(-1)
        return (t % 2 == 1).float(), (t % 3 == 0).float()

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is None:
            self._t.zero_()
        else:
            self._t[mask.reshape(self.num_envs)] = 0
        zeros = torch.zeros(self.num_envs, 1)
        flags = torch.zeros(self.num_envs, 1, dtype=torch.bool)
        return TensorDict(
            {
                "observation": self._observation(),
                "cost": zeros.clone(),
                "cost_info": {"odd": zeros.clone(), "third": zeros.clone()},
                "done": flags.clone(),
                "terminated": flags.clone(),
                "truncated": flags.clone(),
            },
            batch_size=self.batch_size,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self._t += 1
        odd, third = self._costs()
        ended = (self._t >= self.lengths).unsqueeze(-1)
        even_env = (torch.arange(self.num_envs) % 2 == 0).unsqueeze(-1)
        terminated = ended & even_env
        truncated = ended & ~even_env
        return TensorDict(
            {
                "observation": self._observation(),
                "reward": torch.ones(self.num_envs, 1),
                "cost": odd + third,
                "cost_info": {"odd": odd, "third": third},
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
        )

    def _set_seed(self, seed: int | None) -> None:
        return None
