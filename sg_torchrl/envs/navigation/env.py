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

Pixel observations (``obs_mode="rgb"``, ``"rgbd"``, ``"vector+rgb"``, ``"vector+rgbd"``; the
``...Vision-v0`` ids): the robot's ``vision`` camera is rendered after every step and after resets
into ``pixels`` (and ``depth``) entries, next to or instead of ``observation``
(:mod:`sg_torchrl.envs.vision`).

Several robots (a multi-agent task, ``Task.num_agents > 1``: MultiGoal): the world holds one robot per
agent (:attr:`NavigationEnv.robots`, named ``agent_<i>/...`` in the model), the layout places them
first, and reward and costs are computed per agent (``(N, A)`` buffers). The observation is each
robot's sensors, then each robot's lidar groups seen from that robot (Safety-Gymnasium's multi-agent
order). This env's own interface is then the joint control of all robots: the action is every
robot's actuators, the reward and each raw cost the sum over agents. The multi-agent interface is
:class:`sg_torchrl.envs.multi_agent.MultiAgentNavigationEnv` (the registered ids).
"""

from __future__ import annotations

import numpy as np
import torch
from torchrl.data import Composite

from sg_torchrl.envs.base import CostMode, check_num_envs
from sg_torchrl.envs.mujoco_env import MujocoSafeEnv
from sg_torchrl.envs.navigation.layout import LayoutSampler
from sg_torchrl.envs.navigation.lidar import (LidarMode, NaturalLidar, compass_vector, lidar_block, pseudo_lidars,
                                              pseudo_lidars_one)
from sg_torchrl.envs.navigation.objects.base import NavObject
from sg_torchrl.envs.navigation.robots import ROBOTS
from sg_torchrl.envs.navigation.single import SingleNavigationStep
from sg_torchrl.envs.navigation.compose import TaskSpec
from sg_torchrl.envs.navigation.levels import make_task
from sg_torchrl.envs.navigation.tasks import Task
from sg_torchrl.envs.navigation.world import Scene, agent_prefix, build_spec, compiled_model, world_extent
from sg_torchrl.envs.rendering import NAVIGATION_CAMERA, GeomAlpha, RenderMixin
from sg_torchrl.envs.vision import DEFAULT_IMAGE_SIZE, ObservationContent, ObsMode, PixelObserver

__all__ = ["NavigationEnv"]


class NavigationEnv(RenderMixin, MujocoSafeEnv):
    """A navigation task at one level with its robot (one per agent), batched over ``num_envs`` simulators.

    Args:
        robot: a key of :data:`~sg_torchrl.envs.navigation.robots.ROBOTS` (``"Point"``).
        task: a key of :data:`~sg_torchrl.envs.navigation.levels.TASKS` (``"Goal"``), a
            :class:`~sg_torchrl.envs.navigation.compose.TaskSpec` (a task declared as data: each env builds
            its own task from it), or a fresh :class:`~sg_torchrl.envs.navigation.tasks.Task` instance (one
            instance per env, it holds per-simulator state).
        level: the task level (0, 1, 2); ignored when ``task`` is a spec or an instance.
        num_envs, device, seed, cost_mode: see :class:`SafeEnv`.
        max_episode_steps: default: the task's (1000 for Goal).
        lidar: ``"pseudo"`` (default, the reference's) or ``"natural"`` (ray casting, sees the surfaces
            of objects, flat ones included; same size); see :mod:`~sg_torchrl.envs.navigation.lidar`.
        compass: add a 2-value ``<name>_comp`` unit vector to each goal-like object after its lidar
            entry (off by default, as in every reference task; +2 values for the goal).
        obs_mode: ``"vector"`` (default: the flat ``observation``), ``"rgb"`` / ``"rgbd"`` (images
            of the robot's ``vision`` camera only: ``pixels`` and ``depth``), ``"vector+rgb"`` /
            ``"vector+rgbd"`` (both); see :mod:`sg_torchrl.envs.vision`. Single-robot tasks only.
        image_size: side of the square images in pixels (default 256, the reference's; 64 is 16 times cheaper).
        physics_threads: threads stepping the simulators (:class:`~sg_torchrl.envs.physics.MujocoBatch`;
            2 pays when a core is idle, see its module docstring).

    Attributes:
        observation_slices: ``{name: slice}`` of every observation part (``"accelerometer"``, ...,
            ``"goal_lidar"``, ``"hazards_lidar"``, ...).
        layout: ``(N, M, 2)`` the layout each simulator's episode started from (item 0 the agent, items
            ``0 .. A-1`` the agents of a multi-agent task, then
            :attr:`LayoutSampler.slices <sg_torchrl.envs.navigation.layout.LayoutSampler>`).
        scene: the simulators and their state views; ``task``, ``robot``: the composition; ``robots``:
            one robot per agent (``robots[0] is robot``).
    """

    def __init__(
        self,
        robot: str = "Point",
        task: str | TaskSpec | Task = "Goal",
        level: int = 1,
        *,
        num_envs: int = 1,
        device: torch.device | str = "cpu",
        seed: int | list[int] | None = None,
        cost_mode: CostMode = "indicator",
        max_episode_steps: int | None = None,
        lidar: LidarMode = "pseudo",
        compass: bool = False,
        obs_mode: ObsMode = "vector",
        image_size: int = DEFAULT_IMAGE_SIZE,
        physics_threads: int = 1,
    ) -> None:
        content = ObservationContent.parse(obs_mode)  # before building anything, for this message
        check_num_envs(num_envs)  # before building the scene, for this message
        if robot not in ROBOTS:
            raise ValueError(f"unknown navigation robot {robot!r}; choose from {sorted(ROBOTS)}")
        if isinstance(task, TaskSpec):
            task = task.build()
        self.task = task if isinstance(task, Task) else make_task(task, level)
        count = self.task.num_agents
        options = self.task.robot_options.get(robot, {})
        #: the robots, one per agent (``robots[0]`` is :attr:`robot`); several share the world under name prefixes
        self.robots = [ROBOTS[robot](agent_prefix(i, count), **options) for i in range(count)]
        self.robot = self.robots[0]
        objects = self.task.objects
        for obj in objects:
            obj.for_robot(self.robot)  # before the world (and its cache key) is built
        if lidar not in ("pseudo", "natural"):
            raise ValueError(f"lidar must be 'pseudo' or 'natural', got {lidar!r}")
        if not isinstance(compass, bool):  # a string such as "no" is truthy: it would turn the compass on
            raise TypeError(f"compass must be True or False, got {compass!r}")
        # The original's extent: its cameras' clipping planes follow it (world_extent).
        extent = world_extent(self.task.name, self.task.level, max(abs(e) for e in self.task.extents))
        model = compiled_model(  # natural lidar re-assigns geom groups: its own model
            (*self.robot.spec_key(), *self.task.key, ("extent", extent), *((("agents", count),) if count > 1 else ()),
             *(("natural_lidar",) if lidar == "natural" else ())),
            lambda: build_spec(self.robots, objects, self.task.floor_half_size, self.task.scenery, extent),
        )
        for each in self.robots:
            each.bind(model)
        self.scene = Scene(model, num_envs, self.robots, physics_threads=physics_threads)
        self.physics = self.scene.physics
        for obj in objects:
            obj.bind(self.scene)
        agent_keepout = self.robot.keepout if self.task.agent_keepout is None else self.task.agent_keepout
        self.layout_sampler = LayoutSampler(self.task.extents, agent_keepout, objects, self.task.agent_placements,
                                            num_agents=count, label=f"task {self.task.name!r}")
        self.layout = np.zeros((num_envs, self.layout_sampler.size, 2))
        # In-goal-layout items (for re-sampling a goal mid-episode): the agents and every object but movers.
        self._layout_objects = [obj for obj in objects if obj.in_goal_layout]

        # Observation layout: each robot's sensors, then per robot one lidar group per observed object, seen
        # from that robot (Safety-Gymnasium's order, single- and multi-agent). Several robots: the entries of
        # robot i are named "agent_i/<entry>".
        self.observation_slices: dict[str, slice] = {}
        labels = [""] if count == 1 else [f"agent_{i}/" for i in range(count)]
        column = 0
        self._robot_columns: list[slice] = []
        for each, label in zip(self.robots, labels):
            start = column
            for name, width in each.observation_names():
                self.observation_slices[label + name] = slice(column, column + width)
                column += width
            self._robot_columns.append(slice(start, column))
        self._lidar_groups: list[list[tuple[NavObject, slice]]] = []  # per robot
        self._compass_groups: list[list[tuple[NavObject, slice]]] = []
        for label in labels:
            lidar_groups, compass_groups = [], []
            for obj in objects:
                if obj.lidar:
                    part = slice(column, column + self.task.lidar_bins)
                    self.observation_slices[f"{label}{obj.name}_lidar"] = part
                    lidar_groups.append((obj, part))
                    column = part.stop
                if compass and obj.compass_target:
                    part = slice(column, column + 2)
                    self.observation_slices[f"{label}{obj.name}_comp"] = part
                    compass_groups.append((obj, part))
                    column = part.stop
            self._lidar_groups.append(lidar_groups)
            self._compass_groups.append(compass_groups)
        self._natural_lidar = None if lidar == "pseudo" else NaturalLidar(
            self.scene, [obj for obj, _ in self._lidar_groups[0]], num_bins=self.task.lidar_bins,
            max_dist=self.task.lidar_max_dist)
        self._constrained = [obj for obj in objects if obj.cost_names]
        constraint_names = [name for obj in self._constrained for name in obj.cost_names] + list(self.task.cost_names)

        # Hot-path buffers, filled in place (SafeEnv copies what it emits): reward and raw costs per agent.
        self._observation = np.zeros((num_envs, column))
        self._robot_outs = [self._observation[:, columns] for columns in self._robot_columns]  # each robot's sensors
        self._agent_reward = np.zeros((num_envs, count))
        self._agent_costs: dict[str, np.ndarray] = {name: np.zeros((num_envs, count)) for name in constraint_names}
        self._terminated = np.zeros(num_envs, dtype=bool)
        # Per robot, where its pseudo-lidar readings go: one block view of the observation when its groups
        # follow each other (pseudo_lidars then takes every group's maximum in one call), else one view each.
        # One simulator: the block's row as a flat view too, for pseudo_lidars_one (Python floats).
        self._lidar_outs, self._lidar_rows = [], []
        for groups in self._lidar_groups:
            parts = [part for _, part in groups]
            block = lidar_block(self._observation, parts, self.task.lidar_bins)
            self._lidar_outs.append([self._observation[:, part] for part in parts] if block is None else block)
            self._lidar_rows.append(None if block is None or num_envs != 1
                                    else self._observation[0, parts[0].start : parts[-1].stop])
        # What _observe walks every step, zipped once (a one-simulator step pays for each zip it builds).
        self._robot_observers = list(zip(self.robots, self._robot_outs))
        self._observe_views = list(zip(self.scene.views, self._lidar_groups, self._lidar_outs, self._lidar_rows,
                                       self._compass_groups))
        # The robots whose death ends an episode (Robot.can_die), with their scenes; the others are not asked.
        self._mortal = [(each, view) for each, view in zip(self.robots, self.scene.views) if each.can_die]
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
        #: what the observations hold (``obs_mode``); :attr:`vision` renders the images, ``None`` without
        self.obs_content = content
        self.vision: PixelObserver | None = None
        if content.pixels:
            if count > 1:
                raise ValueError(f"obs_mode={obs_mode!r}: pixel observations are for single-robot tasks; "
                                 f"{type(self.task).__name__} has {count} robots")
            self.vision = PixelObserver(self.physics, self.robot.qualified("vision"), image_size, depth=content.depth,
                                        geom_alpha=self.geom_alpha)
            self._declare_pixels()
        self.task.bind(self)
        #: the one-simulator step of :meth:`step_one` (``None``: SafeEnv's, see :mod:`.single`)
        self._single = SingleNavigationStep.of(self, NavigationEnv)

    def step_one(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool, bool, dict[str, float]]:
        """:meth:`SafeEnv.step_one <sg_torchrl.envs.base.SafeEnv.step_one>`, through
        :class:`~sg_torchrl.envs.navigation.single.SingleNavigationStep` where it applies (one simulator,
        one robot, no pixels): the same values, its bookkeeping on Python floats (for single-env speed)."""
        single = self._single
        if single is None:
            return super().step_one(action)
        return single(action)

    def _declare_pixels(self) -> None:
        """Put the image entries in the observation spec (and drop the flat vector in pixels-only modes)."""
        spec = self.observation_spec
        entries = {key: value for key, value in spec.items() if key != "observation" or self.obs_content.vector}
        self.observation_spec = Composite(**entries, **self.vision.specs(self.num_envs, self.device),
                                          shape=spec.shape, device=spec.device)

    def _observation_entries(self, observation: np.ndarray) -> dict[str, torch.Tensor]:
        """The flat vector (``obs_mode`` with ``vector``) and the frames :attr:`vision` last rendered."""
        if self.vision is None:
            return super()._observation_entries(observation)
        entries = super()._observation_entries(observation) if self.obs_content.vector else {}
        entries.update(self.vision.observation())
        return entries

    def close(self, *args, **kwargs):
        if self.vision is not None:
            self.vision.close()
        return super().close(*args, **kwargs)

    default_camera = NAVIGATION_CAMERA  # render(): follows the robot (sg_torchrl.envs.rendering)

    def _render_body(self) -> int:
        return self.scene.agent_body

    def geom_alpha(self, index: int) -> GeomAlpha | None:
        """The task's per-simulator render alphas (the Fading tasks' fading objects), or ``None``."""
        return self.task.geom_alpha(index)

    @property
    def step_costs(self) -> dict[str, np.ndarray]:
        """Each constraint's raw cost of the last step per agent, ``{name: (N, A)}`` (read-only views of
        the env's buffers: tasks read them in :meth:`Task.after_step`, e.g. to show a hazard being paid for)."""
        views = {}
        for name, value in self._agent_costs.items():
            view = value.view()
            view.flags.writeable = False
            views[name] = view
        return views

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
            xy: ``(n, M, 2)`` positions in layout order: item 0 the robot (items ``0 .. A-1`` the
                robots of a multi-agent task, in agent order), then each object's instances at
                ``layout_sampler.slice_of(obj)``. Keep-outs are not checked.
            yaw: ``(n, M)`` headings (default 0: the robot faces +x).
            rngs: one generator per simulator for the robots' spawn noise
                (:meth:`Robot.randomize_pose`, the Ant's; robot 0's draws first); ``None`` starts
                exactly at rest.

        The physics is reset to this layout at rest and the task's episode state restarts (e.g. the
        distance to the goal), and pixel observations (:attr:`vision`) are re-rendered for these
        simulators; step counters are left alone (``reset`` handles those). Used by
        ``reset`` after sampling, and by tests and scripted scenarios.
        """
        scene, sampler = self.scene, self.layout_sampler
        indices = np.atleast_1d(np.asarray(indices, dtype=np.int64))
        xy = np.asarray(xy, dtype=np.float64).reshape(len(indices), sampler.size, 2)
        yaw = np.zeros(xy.shape[:2]) if yaw is None else np.asarray(yaw, dtype=np.float64).reshape(xy.shape[:2])
        rows = scene.reset_buffers(len(indices))
        for item, robot in enumerate(self.robots):
            robot.set_pose(scene.model, rows.qpos, xy[:, item], yaw[:, item])
            if rngs is not None:
                robot.randomize_pose(rows.qpos, rngs)
        for obj in self.task.objects:
            part = sampler.slice_of(obj)
            obj.place(scene, indices, rows, xy[:, part], yaw[:, part])
        self.physics.reset(indices, rows.qpos, rows.qvel, rows.mocap_pos, rows.mocap_quat)
        self.layout[indices] = xy
        self.task.reset(self, indices)
        if self.vision is not None:  # the reset simulators' first frames; the others keep theirs
            self.vision.render(indices)

    def resample(self, obj: NavObject, index: int) -> bool:
        """Move every instance of ``obj`` in simulator ``index`` to a new position (layout keep-out rule).

        The other items are the robots and all objects (movers excepted) at their current
        positions. Returns False if no position was found (the task then ends the episode).
        """
        sampler = self.layout_sampler
        others_xy = [view.agent_xy()[index][None] for view in self.scene.views]
        others_keepout = [sampler.keepouts[: len(self.robots)]]
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
        reward = np.reshape(self.task.reward(self), self._agent_reward.shape)  # one column per agent
        clip = self.task.reward_clip
        if clip is None:
            self._agent_reward[:] = reward
        else:
            np.minimum(np.maximum(reward, -clip), clip, out=self._agent_reward)  # np.clip, cheaper
        views = self.scene.views
        for obj in self._constrained:
            obj.agent_costs(views, self._agent_costs)
        self.task.agent_costs(self, self._agent_costs)
        self._terminated[:] = self.task.after_step(self)
        terminated = self._terminated  # |= on the attribute would reassign it (an nn.Module __setattr__)
        for robot, view in self._mortal:  # one robot dead ends the episode (the reference's rule)
            terminated |= ~robot.is_alive(view)
        if self.vision is not None:  # the state the observation describes (a reached goal already moved)
            self.vision.render(range(self.num_envs))

    def _observe(self) -> np.ndarray:
        scene, obs = self.scene, self._observation
        sensordata = scene.sensordata()
        for robot, out in self._robot_observers:
            robot.observe(sensordata, out)
        max_dist, bins = self.task.lidar_max_dist, self.task.lidar_bins
        natural = self._natural_lidar
        for view, lidar_groups, lidar_outs, lidar_row, compass_groups in self._observe_views:
            position, rotation = view.agent_pos(), view.agent_mat()
            if natural is not None:
                natural.prepare(view)
                for obj, part in lidar_groups:
                    natural.observe(view, obj, out=obs[:, part])
            elif lidar_groups:  # every group in one pass (pseudo_lidars; one simulator: on floats where it applies)
                targets = [obj.positions(scene) for obj, _ in lidar_groups]
                if lidar_row is None or not pseudo_lidars_one(position, rotation, targets, lidar_row, num_bins=bins,
                                                              max_dist=max_dist):
                    pseudo_lidars(position, rotation, targets, lidar_outs, num_bins=bins, max_dist=max_dist)
            for obj, part in compass_groups:
                compass_vector(position, rotation, obj.positions(scene)[:, 0], out=obs[:, part])
        self.task.after_observe(self, obs)
        return obs

    def _compute_reward(self, action: np.ndarray) -> np.ndarray:
        """The (clipped) reward, summed over agents: the single-agent interface of a multi-agent task is
        the team's joint control (the multi-agent env reads the per-agent values)."""
        return self._agent_reward.sum(axis=1)

    def _compute_cost(self) -> dict[str, np.ndarray]:
        """Each constraint's raw cost, summed over agents (one agent: its own)."""
        return {name: value.sum(axis=1) for name, value in self._agent_costs.items()}

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
        if self.vision is not None:
            self.vision.render(range(self.num_envs))
