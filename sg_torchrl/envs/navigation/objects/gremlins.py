"""Gremlins: light boxes that circle their layout positions and must not be touched (Button levels 1-2).

Each gremlin is a free body welded to a mocap body (weld ``solref`` 0.02, 1.5, as the reference).
Before every physics sub-step every mocap is moved to its layout position plus
``travel * (sin t, cos t)``, ``t`` the simulation time, so each gremlin circles its own layout
position with radius ``travel``, all in phase (reference section 6); the robot can still shove a
gremlin off its path for a moment, against the weld. The circles are driven through
:meth:`MujocoBatch.drive_mocap <sg_torchrl.envs.physics.MujocoBatch.drive_mocap>`, vectorised
over simulators and sub-steps.

Height: the reference welds each gremlin to a mocap whose model frame is the world origin and then
drives that mocap at height ``size``, which lifts the box by its own size: it floats one size above
the floor (centre at ``2 * size``) and never touches it. We keep that height, so contacts with the
robot happen as in the reference. A gremlin starts on its circle at the ``t = 0`` point (the
reference starts it at the centre and lets the weld pull it onto the circle during the first step).
"""

from __future__ import annotations

from typing import ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.objects.base import FreeObject, Kind, yaw_quat
from sg_torchrl.envs.navigation.objects.contacts import ContactCost
from sg_torchrl.envs.navigation.world import ResetBuffers, Scene

__all__ = ["Gremlins"]


class Gremlins(ContactCost, FreeObject):
    """``num`` boxes of half-size ``size`` (0.1, density 0.001), keep-out 0.4, circling with radius ``travel`` (0.35).

    The layout position of a gremlin is the centre of its circle (the keep-out contains the
    path). Cost ``"gremlins"`` (reference section 3): the number of robot-gremlin contacts.
    Gremlins are not obstacles for re-sampling a goal (they move).
    """

    name: ClassVar[str] = "gremlins"
    prefix: ClassVar[str] = "gremlin"
    kind: ClassVar[Kind] = "mover"
    in_goal_layout: ClassVar[bool] = False
    weld_solref: ClassVar[tuple[float, float]] = (0.02, 1.5)
    #: how many arrays of sub-step times :meth:`_circle` remembers (a 1000-step episode uses 1000)
    circle_memory: ClassVar[int] = 4096
    rgba: ClassVar[tuple[float, float, float, float]] = (0.5, 0.0, 1.0, 1.0)

    def __init__(self, num: int = 1, *, size: float = 0.1, keepout: float = 0.4, travel: float = 0.35,
                 density: float = 0.001, constrained: bool = True, **options) -> None:
        super().__init__(num, size=size, keepout=keepout, constrained=constrained, **options)
        self.travel = float(travel)
        self.density = float(density)
        self.height = 2.0 * self.size

    def spec_key(self) -> tuple:
        return (*super().spec_key(), self.density)

    def mocap_name(self, i: int) -> str:
        return f"{self.body_name(i)}_mocap"

    def add_to(self, spec: mujoco.MjSpec) -> None:
        super().add_to(spec)  # the free bodies
        relpose = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]  # the body sits exactly at its mocap
        for i in range(self.num):
            spec.worldbody.add_body(name=self.mocap_name(i), mocap=True, pos=[0.0, 0.0, self.height])
            spec.add_equality(name=self.mocap_name(i), type=mujoco.mjtEq.mjEQ_WELD, objtype=mujoco.mjtObj.mjOBJ_BODY,
                              name1=self.mocap_name(i), name2=self.body_name(i),
                              data=[0.0, 0.0, 0.0, *relpose, 1.0, 0.0], solref=list(self.weld_solref))

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_BOX, size=[self.size] * 3,
                      density=self.density, group=0, rgba=list(self.rgba))

    def bind(self, scene: Scene) -> None:
        super().bind(scene)
        model = scene.model
        mocap_bodies = [model.body(self.mocap_name(i)).id for i in range(self.num)]
        self.mocap_ids = model.body_mocapid[mocap_bodies].astype(np.int64)
        #: ``(N, num, 2)`` the circle centres (layout positions) of every simulator
        self.centres = np.zeros((scene.num_envs, self.num, 2))
        self._plans: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray]] = {}  # times shape -> buffer, its xy view
        self._circles: dict[tuple, np.ndarray] = {}  # times -> displacements (_circle)
        scene.physics.drive_mocap(self.mocap_ids, self.trajectory)

    # ------------------------------------------------------------------ motion
    def offset(self, times: np.ndarray) -> np.ndarray:
        """Displacement from the centre at simulation ``times``, ``(*times.shape, 2)``."""
        return self.travel * np.stack([np.sin(times), np.cos(times)], axis=-1)

    def trajectory(self, times: np.ndarray) -> np.ndarray:
        """Mocap targets before the sub-steps starting at ``times`` ``(N, S)``, ``(N, S, num, 3)``.

        The array returned is this object's buffer for that shape, overwritten by the next call: read it
        (or copy it) before calling again. Why: the physics drives the mocaps with it within the step, and
        a one-simulator step is mostly the cost of numpy calls: the buffer's heights are
        written once, and the circle's displacements (:meth:`offset`) are kept per ``times``
        (:meth:`_circle`): each target is its centre plus ``travel * sin(t)`` / ``travel * cos(t)``, as
        ``place`` starts it.
        """
        plan = self._plans.get(times.shape)
        if plan is None:
            targets = np.empty((*times.shape, self.num, 3))
            targets[..., 2] = self.height
            plan = self._plans[times.shape] = (targets, targets[..., :2])
        targets, planar = plan
        np.add(self.centres[:, None], self._circle(times), out=planar)  # both axes in one broadcast sum
        return targets

    def _circle(self, times: np.ndarray) -> np.ndarray:
        """:meth:`offset` of ``times`` as ``(N, S, 1, 2)`` (``travel * sin``, ``travel * cos``), remembered per ``times``.

        Why: a simulator's clock restarts at 0 with each episode and advances by the same sums, so the
        sub-steps of its ``k``-th step start at the same times in every episode; the values are numpy's
        for that very array (computed on its first occurrence). At most :attr:`circle_memory` arrays of
        times are kept (then the memory starts over).
        """
        key = (times.shape, times.tobytes())
        circle = self._circles.get(key)
        if circle is None:
            if len(self._circles) >= self.circle_memory:
                self._circles.clear()
            circle = self._circles[key] = self.offset(times)[:, :, None]
        return circle

    # ------------------------------------------------------------------ layout
    def place(self, scene: Scene, indices: np.ndarray, rows: ResetBuffers, xy: np.ndarray, yaw: np.ndarray) -> None:
        self.centres[indices] = xy
        start = xy + self.offset(np.zeros(1))  # a reset restarts the simulation clock at t = 0
        super().place(scene, indices, rows, start, yaw)
        rows.mocap_pos[:, self.mocap_ids, :2] = start
        rows.mocap_pos[:, self.mocap_ids, 2] = self.height
        rows.mocap_quat[:, self.mocap_ids] = yaw_quat(yaw)

    # ------------------------------------------------------------------ snapshots
    def state_dict(self) -> dict:
        return {"centres": self.centres.copy()}

    def load_state_dict(self, state: dict) -> None:
        self.centres[:] = state["centres"]
