"""``MujocoSafeEnv``: the layer shared by every task simulated with :class:`MujocoBatch`.

:class:`~sg_torchrl.envs.base.SafeEnv` knows nothing about the simulator. Tasks whose simulators
are a :class:`~sg_torchrl.envs.physics.MujocoBatch` held in ``self.physics`` (velocity and
navigation alike) share two facts, kept here once:

* divergence: MuJoCo resets an unstable simulator by itself, so its observation is finite and
  only the physics' instability warnings tell it apart (``physics.unstable``);
* snapshots: the full physics state of every simulator is what checkpoints save;
* ``close`` also stops the physics' stepping threads (``physics_threads`` > 1).
"""

from __future__ import annotations

import numpy as np

from sg_torchrl.envs.base import SafeEnv
from sg_torchrl.envs.physics import MujocoBatch

__all__ = ["MujocoSafeEnv"]


class MujocoSafeEnv(SafeEnv):
    """A :class:`SafeEnv` whose simulators are the :class:`MujocoBatch` ``self.physics``."""

    physics: MujocoBatch

    def _diverged(self, observation: np.ndarray) -> np.ndarray:
        return super()._diverged(observation) | self.physics.unstable

    def _physics_state(self):
        return self.physics.get_state()

    def _load_physics_state(self, state) -> None:
        self.physics.set_state(state)

    def close(self, *args, **kwargs):
        physics = self.__dict__.get("physics")  # absent when the constructor failed early
        if physics is not None:
            physics.close()
        return super().close(*args, **kwargs)
