"""The step as numpy arrays and Python values: the face of :class:`~sg_torchrl.envs.base.SafeEnv`
for the gymnasium / PettingZoo façades and :mod:`sg_torchrl.safety_gymnasium`.

Those step one simulator at a time, where building TensorDicts costs more than the physics. These
public methods give them the TorchRL step's own data as numpy arrays (``step_arrays``,
``output_arrays``) or Python values (``step_one``); they are thin, documented faces of SafeEnv's
private hot path (``_transition_arrays``, ``_aggregate_cost``), which stays free to change.
"""

from __future__ import annotations

import numpy as np

from sg_torchrl.envs.step_hooks import step_hook

__all__ = ["NumpyStepInterface"]


class NumpyStepInterface:
    """Mixin of :class:`~sg_torchrl.envs.base.SafeEnv`: its step without TensorDicts (module docstring)."""

    def step_arrays(self, action: np.ndarray) -> tuple:
        """One batched step on numpy arrays: the TorchRL ``step`` without TensorDicts.

        Args:
            action: the ``(N, act_dim)`` float64 action (the caller has checked its shape and that
                it is finite; it is clipped to the bounds here, as in ``step``).

        Returns:
            ``(observation, reward, costs, terminated, truncated)``: ``observation`` ``(N, obs_dim)``,
            ``reward`` ``(N,)`` (or ``(N, A)`` per agent), ``costs`` the raw per-constraint costs
            (:meth:`output_arrays` turns them into the emitted ``cost`` / ``cost_info``), the
            flags ``(N,)`` bool. The values are float64: the TorchRL step emits them as float32.
            The arrays may be buffers that the next step overwrites: copy what you keep.
        """
        return self._transition_arrays(action)

    def step_one(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool, bool, dict[str, float]]:
        """One step of a one-simulator env as Python values: what a gymnasium env returns.

        Args:
            action: the ``(act_dim,)`` or ``(1, act_dim)`` action (the caller has checked its shape and
                that it is finite; it is clipped to the bounds here, as in ``step``).

        Returns:
            ``(observation, reward, cost, terminated, truncated, cost_info)``: the ``(obs_dim,)`` float64
            observation, reward and cost as Python floats, the flags as Python bools and ``cost_info``
            ``{name: float}``. Each value is the float32 value the TorchRL ``step`` emits, widened
            (the observation a fresh array), so a policy sees the same inputs through either API.
        """
        if self.num_envs != 1:
            raise ValueError(f"step_one steps a one-simulator env; this one has num_envs={self.num_envs}")
        return self._single_outputs(*self._transition_arrays(np.asarray(action, dtype=np.float64).reshape(1, -1)))

    @step_hook
    def _single_outputs(self, observation, reward, costs, terminated, truncated) -> tuple:
        """:meth:`step_one`'s values from :meth:`_transition_arrays`' arrays of one simulator."""
        f32 = np.float32
        cost, cost_info = self._single_cost({name: value.item(0) for name, value in costs.items()})
        return (
            observation[0].astype(f32).astype(np.float64),
            float(f32(reward.item(0))),
            cost,
            bool(terminated[0]),
            bool(truncated[0]),
            cost_info,
        )

    @step_hook
    def _single_cost(self, raw: dict[str, float]) -> tuple[float, dict[str, float]]:
        """One simulator's emitted ``(cost, cost_info)`` from its raw costs as Python floats: :meth:`_aggregate_cost`'s
        values (the same float64 sum from 0 in the same order, the same ``> 0`` indicators, float32 rounding)
        without one-element arrays per constraint (for single-env speed)."""
        total = 0.0
        for value in raw.values():
            total += value
        if self.cost_mode == "indicator":
            return 1.0 if total > 0 else 0.0, {name: 1.0 if value > 0 else 0.0 for name, value in raw.items()}
        f32 = np.float32
        return float(f32(total)), {name: float(f32(value)) for name, value in raw.items()}

    def output_arrays(self, observation, reward, costs, terminated, truncated) -> dict:
        """The step's output, as :meth:`step` would emit it under ``"next"``, as nested numpy arrays.

        Takes :meth:`step_arrays`' tuple (``reward=None``: a reset's output, without ``reward``) and
        returns what ``env.step(td)["next"].numpy()`` would hold (float32 values, ``(N, 1)`` columns,
        ``cost_info`` as a nested dict); multi-agent envs add their group and ``state`` in their own
        layout. Every array is fresh. Envs whose observations are not only the flat vector (pixels,
        :mod:`sg_torchrl.envs.vision`) emit more entries than this: step those through ``step``.
        """
        own_layout = getattr(self, "_output_arrays", None)  # multi-agent envs (AgentGroupMixin)
        if own_layout is not None:
            return own_layout(observation, reward, costs, terminated, truncated)
        cost, cost_info = self._aggregate_cost(costs)
        n = self.num_envs

        def column(values, dtype: type) -> np.ndarray:
            return np.array(values, dtype=dtype).reshape(n, -1)

        out = {
            "observation": column(observation, np.float32),
            "cost": column(cost, np.float32),
            "cost_info": {name: column(value, np.float32) for name, value in cost_info.items()},
            "terminated": column(terminated, np.bool_),
            "truncated": column(truncated, np.bool_),
            "done": column(np.logical_or(terminated, truncated), np.bool_),
        }
        if reward is not None:
            out["reward"] = column(reward, np.float32)
        return out
