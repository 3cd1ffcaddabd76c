"""Contact costs: objects that must not be touched by the robot (pillars, gremlins)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from sg_torchrl.envs.navigation.objects.base import NamedCost

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.world import Scene

__all__ = ["ContactCost", "robot_contacts"]


def robot_contacts(scene: Scene, geom_mask: np.ndarray) -> np.ndarray:
    """Number of contacts between the robot and the geoms of ``geom_mask`` (``(ngeom,)`` bool), ``(N,)``."""
    return scene.robot_contacts()[:, geom_mask].sum(axis=1)


class ContactCost(NamedCost):
    """Mixin for a :class:`~sg_torchrl.envs.navigation.objects.base.NavObject`: when constrained, one cost
    entry named after the object, the number of MuJoCo contacts between its geoms and the robot's
    (reference section 3: ``cost_pillars``, ``cost_gremlins``; coefficient 1)."""

    geom_mask: np.ndarray

    def bind(self, scene: Scene) -> None:
        super().bind(scene)
        self._contact_geoms = frozenset(np.flatnonzero(self.geom_mask).tolist())  # see cost_one

    def cost(self, scene: Scene) -> np.ndarray:
        return robot_contacts(scene, self.geom_mask)

    def cost_one(self, scene: Scene) -> float:
        """The contact counts of this object's geoms among the robot's few contacts
        (:meth:`Scene.robot_contacts_one <sg_torchrl.envs.navigation.world.Scene.robot_contacts_one>`),
        summed from 0: whole numbers, the same sum as the array form's in any order."""
        total, geoms = 0.0, self._contact_geoms
        for geom, count in scene.robot_contacts_one().items():
            if geom in geoms:
                total += count
        return total
