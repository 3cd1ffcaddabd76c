"""Task objects (see :mod:`.base`): goal and constraints, each owning placement, geometry and cost.

Still to come for the other navigation tasks: ``Pillars`` (static, collide, contact cost),
``Buttons`` (static, collide, contact cost for a wrong button), ``PushBox`` (free), ``Gremlins``
(mover: mocap welded to a free body, contact cost), ``Sigwalls`` (out-of-boundary cost, not
observed) and ``Circle`` (static zone, lidar max distance 6).
"""

from sg_torchrl.envs.navigation.objects.base import FreeObject, NavObject, StaticObject, yaw_quat
from sg_torchrl.envs.navigation.objects.goal import Goal
from sg_torchrl.envs.navigation.objects.hazards import Hazards
from sg_torchrl.envs.navigation.objects.vases import Vases

__all__ = ["FreeObject", "Goal", "Hazards", "NavObject", "StaticObject", "Vases", "yaw_quat"]
