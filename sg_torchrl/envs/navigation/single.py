"""One navigation simulator stepped on Python values: the gymnasium façade's step, for single-env speed.

:meth:`SafeEnv.step_one <sg_torchrl.envs.base.SafeEnv.step_one>` runs the batched step
(:meth:`~sg_torchrl.envs.base.SafeEnv._transition_arrays`) on ``N = 1`` and reads its outputs. On one
simulator of a small robot that batched bookkeeping (the reward's clip and its sum over agents, the
costs' sums over agents, the termination flags, the step counter, the fault screen's reductions, the
``(N,)`` arrays of each) costs as much as a third of the physics: each numpy call on a one-element array
costs about a microsecond whatever it computes. :class:`SingleNavigationStep` is that step for one
simulator of a single-robot :class:`~sg_torchrl.envs.navigation.env.NavigationEnv`, with the bookkeeping
on Python floats and bools:

* the physics, the task's and objects' reward, cost and event hooks and the observation are the env's
  own (:meth:`Task.reward_one <sg_torchrl.envs.navigation.tasks.base.Task.reward_one>`,
  :meth:`Task.after_step_one <sg_torchrl.envs.navigation.tasks.base.Task.after_step_one>` and
  :meth:`NavObject.agent_costs_one <sg_torchrl.envs.navigation.objects.base.NavObject.agent_costs_one>`
  are the one-simulator faces of ``reward``, ``after_step`` and ``agent_costs``: by default the batched
  hooks themselves; the Goal tasks' shaping and goal events, the Button task's goal press and timer, the
  hazards' depths and the buttons' and contact costs (from the robot's contacts counted once per step,
  :meth:`Scene.robot_contacts_one <sg_torchrl.envs.navigation.world.Scene.robot_contacts_one>`) are
  computed on Python values, as is the pseudo-lidar of the observation
  (:func:`~sg_torchrl.envs.navigation.lidar.pseudo_lidars_one`), each with one formula or with its two
  forms documented and tested equal);
* what :class:`~sg_torchrl.envs.navigation.env.NavigationEnv` and
  :class:`~sg_torchrl.envs.base.SafeEnv` do around them is done here on floats with the same float64
  operations in the same order: the action's clip (:meth:`SingleNavigationStep._clip`, written straight
  into ``MjData``), the reward's clip (``min``/``max`` keep NaN as ``np.minimum``/``np.maximum``
  do), the sum over one agent (the value itself), the step counter and truncation, the fault screen's
  magnitude (:func:`~sg_torchrl.envs.base._magnitude`'s sum) and the cost aggregation
  (:meth:`SafeEnv._single_cost <sg_torchrl.envs.base.SafeEnv._single_cost>`, shared with the batched
  path's one-simulator outputs);
* the env's buffers that tasks and snapshots read (the per-agent reward and costs, the termination flags,
  the step counter) are filled as the batched step fills them;
* a faulty step (an unstable simulator, a non-finite observation or outcome) goes through the env's own
  exact test and isolation on the arrays the batched step would have had.

``tests/test_single_env_path.py`` checks that the façade (this path), the TorchRL env at ``N = 1`` and
simulator 0 of a batched env emit the same values bit for bit; ``tests/test_button_speed_paths.py``
checks the Button level's float forms against their array forms.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from sg_torchrl.envs.base import FLOAT32_MAX

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv

__all__ = ["SingleNavigationStep"]


class SingleNavigationStep:
    """:meth:`SafeEnv.step_one <sg_torchrl.envs.base.SafeEnv.step_one>` of ``env``, bookkeeping on Python values.

    Build it with :meth:`of`, which answers ``None`` for the envs it does not cover: more than one
    simulator or robot, pixel observations, a physics backend without the aliased single step
    (:attr:`PhysicsBatch.supports_aliased_single_step <sg_torchrl.envs.physics_protocol.PhysicsBatch>`), or
    an env class that redefines one of the step hooks it does the work of
    (:meth:`~sg_torchrl.envs.step_hooks.StepHooks.hooks_overridden_since`).
    """

    def __init__(self, env: NavigationEnv) -> None:
        self.env = env
        self._clipped = np.zeros((1, env.action_dim))
        self._ctrl = env.physics.datas[0].ctrl[None]  # (1, nu) view of the one simulator's control
        # The clip on Python floats (see _clip), unless a bound is zero: there np.maximum / np.minimum may pick
        # either of -0.0 and +0.0 (a SIMD max returns one operand on ties), which a comparison cannot promise.
        low, high = env._clip_low.reshape(-1).tolist(), env._clip_high.reshape(-1).tolist()
        self._bounds = None if 0.0 in low or 0.0 in high else list(zip(low, high))
        self._agent_costs = list(env._agent_costs.items())  # {name: (1, 1)} buffers, in constraint order
        self._row = env._observation[0]  # the one simulator's observation row (NavigationEnv._observe's buffer)

    @classmethod
    def of(cls, env: NavigationEnv, written_for: type[NavigationEnv]) -> SingleNavigationStep | None:
        """This step for ``env``, or ``None`` where it does not apply; ``written_for`` is the env class whose
        hooks it reproduces (:class:`~sg_torchrl.envs.navigation.env.NavigationEnv`, which passes itself)."""
        if (env.num_envs != 1 or len(env.robots) != 1 or env.vision is not None
                or not env.physics.supports_aliased_single_step or type(env).hooks_overridden_since(written_for)):
            return None
        return cls(env)

    def __call__(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool, bool, dict[str, float]]:
        env = self.env
        task, scene, physics = env.task, env.scene, env.physics
        # SafeEnv._transition_arrays: the clip (np.clip's values) written straight into MjData's control, then
        # NavigationEnv._advance through the physics' aliased single step.
        if not self._clip(action):
            clipped = self._clipped
            np.maximum(action, env._clip_low, out=clipped)  # (act_dim,) or (1, act_dim): the same (1, act_dim) row
            np.minimum(clipped, env._clip_high, out=self._ctrl)
        unstable = physics.advance_one(env.frame_skip)
        reward = task.reward_one(env)
        clip = task.reward_clip
        if clip is not None:
            reward = min(max(reward, -clip), clip)  # np.clip's value, NaN kept
        agent_reward = env._agent_reward
        agent_reward[0, 0] = reward
        reward = agent_reward.item(0)  # the float64 value the batched step reads (one agent: its own)
        buffers = env._agent_costs
        for obj in env._constrained:
            obj.agent_costs_one(scene, buffers)
        task.agent_costs(env, buffers)
        raw = {}  # one agent: its sum is its value (a loop: cheaper than a comprehension's frame)
        for name, buffer in self._agent_costs:
            raw[name] = buffer.item(0)
        terminated = task.after_step_one(env)
        for robot, view in env._mortal:
            terminated = terminated or not robot.is_alive(view)[0]
        env._terminated[0] = terminated
        observation = env._observe()
        # SafeEnv: the step counter, truncation and the fault screen (MujocoSafeEnv's and SafeEnv's _fault_free).
        elapsed = env._elapsed
        steps = elapsed.item(0) + 1
        elapsed[0] = steps
        truncated = steps >= env.max_episode_steps
        magnitude = abs(reward)
        for value in raw.values():
            magnitude += abs(value)
        # The row's sum is finite only when every entry is (in any order: an overflow only sends the step to
        # the exact test below, which finds the same values).
        row = self._row
        if not unstable and math.isfinite(np.add.reduce(row)) and magnitude <= FLOAT32_MAX:
            cost, cost_info = env._single_cost(raw)
            return (row.astype(np.float32).astype(np.float64), float(np.float32(reward)), cost,
                    terminated, truncated, cost_info)
        # A faulty step: the env's exact test and isolation on the arrays of the batched step.
        rewards = np.array((reward,))
        costs = {name: np.array((value,)) for name, value in raw.items()}
        flags = np.array((terminated,)), np.array((truncated,))
        diverged = env._diverged(observation) | env._nonfinite_outcome(rewards, costs)
        if diverged.any():
            return env._single_outputs(*env._isolate(diverged, observation, rewards, costs, *flags))
        return env._single_outputs(observation, rewards, costs, *flags)

    def _clip(self, action: np.ndarray) -> bool:
        """Write ``action`` clipped to the control bounds into ``MjData``'s control on Python floats; False
        (nothing written) where the array form must do it: a bound at zero, or an action of another size
        (the array form then raises as before).

        The same values as ``np.minimum(np.maximum(action, low), high)``: float32 actions widen to float64
        exactly either way, and raising a value below ``low`` to ``low`` then lowering one above ``high`` to
        ``high`` picks the same number whenever the operands differ or are equal non-zeros; NaN stays NaN
        (both comparisons fail, as ``np.maximum`` / ``np.minimum`` propagate it)."""
        bounds = self._bounds
        values = action.reshape(-1).tolist()
        if bounds is None or len(values) != len(bounds):
            return False
        clipped = []
        for value, (low, high) in zip(values, bounds):
            if value < low:
                value = low
            if value > high:
                value = high
            clipped.append(value)
        self._ctrl[0] = clipped
        return True
