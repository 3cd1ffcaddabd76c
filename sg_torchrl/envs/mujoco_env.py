"""``MujocoSafeEnv``: the layer shared by every task simulated with :class:`MujocoBatch`.

:class:`~sg_torchrl.envs.base.SafeEnv` knows nothing about the simulator. Tasks whose simulators
are a :class:`~sg_torchrl.envs.physics.MujocoBatch` (or its MuJoCo Warp twin
:class:`~sg_torchrl.envs.warp_physics.WarpBatch`, see :mod:`sg_torchrl.envs.backends`) held in
``self.physics`` (velocity, navigation and the two-hand tasks alike) share these facts, kept here once:

* divergence: the physics resets an unstable simulator by itself, so its observation is finite and
  only ``physics.unstable`` tells it apart;
* snapshots: the full physics state of every simulator is what checkpoints save;
* ``close`` also stops the physics' stepping threads (``physics_threads`` > 1).
"""

from __future__ import annotations

import numpy as np

from sg_torchrl.envs.base import SafeEnv
from sg_torchrl.envs.physics_protocol import PhysicsBatch

__all__ = ["MujocoSafeEnv"]


class MujocoSafeEnv(SafeEnv):
    """A :class:`SafeEnv` whose simulators are the physics batch ``self.physics`` (either backend)."""

    physics: PhysicsBatch

    def _diverged(self, observation: np.ndarray) -> np.ndarray:
        return super()._diverged(observation) | self.physics.unstable

    def _fault_free(self, observation: np.ndarray, reward: np.ndarray, costs: dict[str, np.ndarray]) -> bool:
        return not np.count_nonzero(self.physics.unstable) and super()._fault_free(observation, reward, costs)

    def _physics_state(self):
        return self.physics.get_state()

    def _load_physics_state(self, state) -> None:
        self.physics.set_state(state)

    def close(self, *args, **kwargs):
        physics = self.__dict__.get("physics")  # absent when the constructor failed early
        if physics is not None:
            physics.close()
        return super().close(*args, **kwargs)
