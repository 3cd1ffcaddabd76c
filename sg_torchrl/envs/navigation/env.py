"""``NavigationEnv``: Safety-Gymnasium's safe navigation tasks, N simulators per env.

``Safety{Robot}{Task}{Level}-v0`` = a robot (:mod:`.robots`) in a world holding a task level's
objects (:mod:`.objects`, :mod:`.tasks`). The world is compiled once per (robot, task, level) and
shared; each reset samples a layout with the simulator's own generator and writes it into
``MjData`` (:mod:`.world`, :mod:`.layout`).

Per step (reference sections 2-6): the clipped action is the control of every actuator for 10
physics steps, then a forward pass; the task's reward (clipped to +-10) and each constrained
object's raw cost are computed on that state; then task events (a reached goal moves) and the
observation: robot sensors, then one 16-bin pseudo-lidar per lidar-observed object in world order
(:attr:`NavigationEnv.observation_slices` names every part). ``cost`` is the indicator of the summed
raw costs by default (``cost_mode="raw"``: the sum itself); ``cost_info`` holds one entry per
constraint, e.g. ``hazards``, ``vases_contact``, ``vases_velocity``.
"""

from __future__ import annotations

import numpy as np
import torch

from sg_torchrl.envs.base import CostMode
from sg_torchrl.envs.mujoco_env import MujocoSafeEnv
from sg_torchrl.envs.navigation.layout import LayoutSampler
from sg_torchrl.envs.navigation.lidar import LidarMode, NaturalLidar, compass_vector, pseudo_lidar
from sg_torchrl.envs.navigation.objects.base import NavObject
from sg_torchrl.envs.navigation.robots import ROBOTS
from sg_torchrl.envs.navigation.tasks import Task, make_task
from sg_torchrl.envs.navigation.world import Scene, build_spec, compiled_model
from sg_torchrl.envs.rendering import NAVIGATION_CAMERA, RenderMixin

__all__ = ["NavigationEnv"]


class NavigationEnv(RenderMixin, MujocoSafeEnv):
    """A navigation task at one level with one robot, batched over ``num_envs`` simulators.

    Args:
        robot: a key of :data:`~sg_torchrl.envs.navigation.robots.ROBOTS` (``"Point"``).
        task: a key of :data:`~sg_torchrl.envs.navigation.tasks.TASKS` (``"Goal"``), or a fresh
            :class:`~sg_torchrl.envs.navigation.tasks.Task` instance (a custom composition; one
            instance per env, it holds per-simulator state).
        level: the task level (0, 1, 2); ignored when ``task`` is an instance.
        num_envs, device, seed, cost_mode: see :class:`SafeEnv`.
        max_episode_steps: default: the task's (1000 for Goal).
        lidar: ``"pseudo"`` (default, the reference's) or ``"natural"`` (ray casting, sees the surfaces
            of objects, flat ones included; same size); see :mod:`~sg_torchrl.envs.navigation.lidar`.
        compass: add a 2-value ``<name>_comp`` unit vector to each goal-like object after its lidar
            entry (off by default, as in every reference task; +2 values for the goal).

    Attributes:
        observation_slices: ``{name: slice}`` of every observation part (``"accelerometer"``, ...,
            ``"goal_lidar"``, ``"hazards_lidar"``, ...).
        layout: ``(N, M, 2)`` the layout each simulator's episode started from (item 0 the agent,
            then :attr:`LayoutSampler.slices <sg_torchrl.envs.navigation.layout.LayoutSampler>`).
        scene: the simulators and their state views; ``task``, ``robot``: the composition.
    """

    def __init__(
        self,
        robot: str = "Point",
        task: str | Task = "Goal",
        level: int = 1,
        *,
        num_envs: int = 1,
        device: torch.device | str = "cpu",
        seed: int | None = None,
        cost_mode: CostMode = "indicator",
        max_episode_steps: int | None = None,
        lidar: LidarMode = "pseudo",
        compass: bool = False,
    ) -> None:
        if not isinstance(num_envs, int) or num_envs < 1:  # before building the scene, for this message
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if robot not in ROBOTS:
            raise ValueError(f"unknown navigation robot {robot!r}; choose from {sorted(ROBOTS)}")
        self.robot = ROBOTS[robot]()
        self.task = task if isinstance(task, Task) else make_task(task, level)
        objects = self.task.objects
        for obj in objects:
            obj.for_robot(self.robot)  # before the world (and its cache key) is built
        if lidar not in ("pseudo", "natural"):
            raise ValueError(f"lidar must be 'pseudo' or 'natural', got {lidar!r}")
        model = compiled_model(  # natural lidar re-assigns geom groups: its own model
            (self.robot.name, *self.task.key, *(("natural_lidar",) if lidar == "natural" else ())),
            lambda: build_spec(self.robot, objects, self.task.floor_half_size),
        )
        self.robot.bind(model)
        self.scene = Scene(model, num_envs, self.robot)
        self.physics = self.scene.physics
        for obj in objects:
            obj.bind(self.scene)
        agent_keepout = self.robot.keepout if self.task.agent_keepout is None else self.task.agent_keepout
        self.layout_sampler = LayoutSampler(self.task.extents, agent_keepout, objects, self.task.agent_placements)
        self.layout = np.zeros((num_envs, self.layout_sampler.size, 2))
        # In-goal-layout items (for re-sampling a goal mid-episode): the agent and every object but movers.
        self._layout_objects = [obj for obj in objects if obj.in_goal_layout]

        # Observation layout: robot sensors, then one lidar group per observed object.
        self.observation_slices: dict[str, slice] = {}
        column = 0
        for name, width in self.robot.observation_names():
            self.observation_slices[name] = slice(column, column + width)
            column += width
        self._robot_columns = slice(0, column)
        self._lidar_groups: list[tuple[NavObject, slice]] = []
        self._compass_groups: list[tuple[NavObject, slice]] = []
        for obj in objects:
            if obj.lidar:
                part = slice(column, column + self.task.lidar_bins)
                self.observation_slices[f"{obj.name}_lidar"] = part
                self._lidar_groups.append((obj, part))
                column = part.stop
            if compass and obj.compass_target:
                part = slice(column, column + 2)
                self.observation_slices[f"{obj.name}_comp"] = part
                self._compass_groups.append((obj, part))
                column = part.stop
        self._natural_lidar = None if lidar == "pseudo" else NaturalLidar(
            self.scene, [obj for obj, _ in self._lidar_groups], num_bins=self.task.lidar_bins,
            max_dist=self.task.lidar_max_dist)
        self._constrained = [obj for obj in objects if obj.cost_names]
        constraint_names = [name for obj in self._constrained for name in obj.cost_names]

        # Hot-path buffers, filled in place (SafeEnv copies what it emits).
        self._observation = np.zeros((num_envs, column))
        self._reward = np.zeros(num_envs)
        self._costs: dict[str, np.ndarray] = {name: np.zeros(num_envs) for name in constraint_names}
        self._terminated = np.zeros(num_envs, dtype=bool)
        low, high = self.physics.ctrl_range
        super().__init__(
            num_envs=num_envs,
            observation_dim=column,
            action_low=low,
            action_high=high,
            constraint_names=constraint_names,
            max_episode_steps=self.task.max_episode_steps if max_episode_steps is None else max_episode_steps,
            frame_skip=self.robot.frame_skip,
            cost_mode=cost_mode,
            device=device,
            seed=seed,
        )
        self.task.bind(self)

    default_camera = NAVIGATION_CAMERA  # render(): follows the robot (sg_torchrl.envs.rendering)

    def _render_body(self) -> int:
        return self.scene.agent_body

    # ------------------------------------------------------------------ layout
    def _reset_sims(self, indices: np.ndarray) -> None:
        sampler = self.layout_sampler
        xy = np.empty((len(indices), sampler.size, 2))
        yaw = np.empty((len(indices), sampler.size))
        for row, index in enumerate(indices):
            xy[row], yaw[row] = sampler.sample(self._rngs[index])
        self.set_layout(indices, xy, yaw, rngs=[self._rngs[index] for index in indices])

    def set_layout(self, indices, xy: np.ndarray, yaw: np.ndarray | None = None,
                   rngs: list[np.random.Generator] | None = None) -> None:
        """Start simulators ``indices`` from a given layout instead of a sampled one.

        Args:
            indices: simulator indices (``n`` of them).
            xy: ``(n, M, 2)`` positions in layout order: item 0 the robot, then each object's
                instances at ``layout_sampler.slice_of(obj)``. Keep-outs are not checked.
            yaw: ``(n, M)`` headings (default 0: the robot faces +x).
            rngs: one generator per simulator for the robot's spawn noise
                (:meth:`Robot.randomize_pose`, the Ant's); ``None`` starts exactly at rest.

        The physics is reset to this layout at rest and the task's episode state restarts (e.g. the
        distance to the goal); step counters are left alone (``reset`` handles those). Used by
        ``reset`` after sampling, and by tests and scripted scenarios.
        """
        scene, sampler = self.scene, self.layout_sampler
        indices = np.atleast_1d(np.asarray(indices, dtype=np.int64))
        xy = np.asarray(xy, dtype=np.float64).reshape(len(indices), sampler.size, 2)
        yaw = np.zeros(xy.shape[:2]) if yaw is None else np.asarray(yaw, dtype=np.float64).reshape(xy.shape[:2])
        rows = scene.reset_buffers(len(indices))
        self.robot.set_pose(scene.model, rows.qpos, xy[:, 0], yaw[:, 0])
        if rngs is not None:
            self.robot.randomize_pose(rows.qpos, rngs)
        for obj in self.task.objects:
            part = sampler.slice_of(obj)
            obj.place(scene, indices, rows, xy[:, part], yaw[:, part])
        self.physics.reset(indices, rows.qpos, rows.qvel, rows.mocap_pos, rows.mocap_quat)
        self.layout[indices] = xy
        self.task.reset(self, indices)

    def resample(self, obj: NavObject, index: int) -> bool:
        """Move every instance of ``obj`` in simulator ``index`` to a new position (layout keep-out rule).

        The other items are the robot and all objects (movers excepted) at their current
        positions. Returns False if no position was found (the task then ends the episode).
        """
        sampler = self.layout_sampler
        others_xy = [self.scene.agent_xy()[index][None]]
        others_keepout = [sampler.keepouts[:1]]
        for other in self._layout_objects:
            if other is not obj:
                others_xy.append(other.positions(self.scene)[index])
                others_keepout.append(sampler.keepouts[sampler.slice_of(other)])
        others_xy, others_keepout = np.concatenate(others_xy), np.concatenate(others_keepout)
        part = sampler.slice_of(obj)
        for instance, item in enumerate(range(part.start, part.stop)):
            xy = sampler.resample(self._rngs[index], item, others_xy, others_keepout)
            if xy is None:
                return False
            obj.move(self.scene, index, instance, xy)
            others_xy = np.concatenate([others_xy, xy[None]])
            others_keepout = np.append(others_keepout, sampler.keepouts[item])
        return True

    def rng(self, index: int) -> np.random.Generator:
        """Simulator ``index``'s generator: layouts, goal positions and every other random event of a task
        draw from it, so a seed replays a simulator whatever ``num_envs`` is."""
        return self._rngs[index]

    # ------------------------------------------------------------------ stepping
    def _advance(self, action: np.ndarray) -> None:
        self.physics.step(action, self.frame_skip)
        # Reward, then costs, on the state the physics ended in; then task events (a reached goal
        # moves), so that the observation below already shows the new goal.
        reward = self.task.reward(self)
        clip = self.task.reward_clip
        if clip is None:
            self._reward[:] = reward
        else:
            np.clip(reward, -clip, clip, out=self._reward)
        for obj in self._constrained:
            for name, value in obj.costs(self.scene).items():
                self._costs[name][:] = value
        self._terminated[:] = self.task.after_step(self)
        self._terminated |= ~self.robot.is_alive(self.scene)

    def _observe(self) -> np.ndarray:
        scene, obs = self.scene, self._observation
        self.robot.observe(scene.sensordata(), obs[:, self._robot_columns])
        position, rotation = scene.agent_pos(), scene.agent_mat()
        max_dist, bins = self.task.lidar_max_dist, self.task.lidar_bins
        natural = self._natural_lidar
        if natural is not None:
            natural.prepare(scene)
        for obj, part in self._lidar_groups:
            if natural is not None:
                natural.observe(scene, obj, out=obs[:, part])
            else:
                pseudo_lidar(position, rotation, obj.positions(scene), num_bins=bins, max_dist=max_dist,
                             out=obs[:, part])
        for obj, part in self._compass_groups:
            compass_vector(position, rotation, obj.positions(scene)[:, 0], out=obs[:, part])
        self.task.after_observe(self, obs)
        return obs

    def _compute_reward(self, action: np.ndarray) -> np.ndarray:
        return self._reward

    def _compute_cost(self) -> dict[str, np.ndarray]:
        return self._costs

    def _compute_terminated(self) -> np.ndarray:
        return self._terminated


    # ------------------------------------------------------------------ snapshots
    def _physics_state(self):
        # Mocap positions (goal, hazards, ...) are not part of MuJoCo's physics state; save them too.
        return {
            "physics": self.physics.get_state(),
            "mocap_pos": self.physics.gather("mocap_pos"),
            "mocap_quat": self.physics.gather("mocap_quat"),  # yawed mocaps the physics follows (gremlins)
            "objects": {obj.name: obj.state_dict() for obj in self.task.objects},
            "layout": self.layout.copy(),
            "task": self.task.state_dict(),
        }

    def _load_physics_state(self, state) -> None:
        for index, rows in enumerate(state["mocap_pos"]):
            for mocap_id, pos in enumerate(rows):
                self.physics.set_mocap_pos(index, mocap_id, pos)
        for data, quat in zip(self.physics.datas, state.get("mocap_quat", ())):
            data.mocap_quat[:] = quat
        self.physics.set_state(state["physics"])
        for obj in self.task.objects:
            obj.load_state_dict(state["objects"][obj.name])
        self.layout[:] = state["layout"]
        self.task.load_state_dict(state["task"])
