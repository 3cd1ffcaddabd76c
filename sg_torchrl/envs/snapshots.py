"""Simulator snapshots and env copies, a part of :class:`~sg_torchrl.envs.base.SafeEnv`.

* :meth:`SimulatorSnapshots.sim_state`: the generators, step counters and physics of every simulator.
  Checkpoints save it so that a resumed run replays the uninterrupted one bit for bit.
* Copies (``copy.deepcopy``, ``pickle``) copy numpy views as separate arrays, so a copied env's caches,
  buffers and control views would no longer alias its ``MjData`` and the copy would step wrongly. An
  env built by ``sg_torchrl.make`` remembers how; its copies are new envs built the same way whose
  simulators continue from its ``sim_state``: given the same action, the copy's next step equals the original's.
"""

from __future__ import annotations

__all__ = ["SimulatorSnapshots"]


class SimulatorSnapshots:
    """Mixin of :class:`~sg_torchrl.envs.base.SafeEnv` (which holds ``num_envs``, the per-simulator
    generators ``_rngs`` and step counters ``_elapsed``); a task supplies :meth:`_physics_state` and
    :meth:`_load_physics_state` (``MujocoSafeEnv`` does for every MuJoCo task)."""

    # ------------------------------------------------------------------ snapshots
    def sim_state(self) -> dict:
        """Everything needed to continue the simulators exactly: generators, step counters, physics."""
        return {
            "rngs": [rng.bit_generator.state for rng in self._rngs],
            "elapsed": self._elapsed.copy(),
            "physics": self._physics_state(),
        }

    def load_sim_state(self, state: dict) -> None:
        """Restore :meth:`sim_state` output."""
        if len(state["rngs"]) != self.num_envs:
            raise ValueError(f"state holds {len(state['rngs'])} simulators, this env has {self.num_envs}")
        for rng, rng_state in zip(self._rngs, state["rngs"]):
            rng.bit_generator.state = rng_state
        self._elapsed[:] = state["elapsed"]
        self._load_physics_state(state["physics"])

    def _physics_state(self):
        """Task hook: a picklable snapshot of the simulators (see ``MujocoSafeEnv``)."""
        raise NotImplementedError(f"{type(self).__name__} does not support simulator snapshots")

    def _load_physics_state(self, state) -> None:
        raise NotImplementedError(f"{type(self).__name__} does not support simulator snapshots")

    # ------------------------------------------------------------------ copies
    def remember_construction(self, constructor, kwargs: dict) -> None:
        """Record how this env was built (``sg_torchrl.make`` does), so that copies can rebuild it."""
        self.__dict__["_construction"] = (constructor, dict(kwargs))

    def __reduce_ex__(self, protocol):
        """Copies and pickles of an env built by ``sg_torchrl.make``: rebuilt, then :meth:`load_sim_state`.

        Envs built otherwise, or whose task has no simulator snapshot, are copied attribute by attribute.
        """
        construction = self.__dict__.get("_construction")
        if construction is not None:
            try:
                state = self.sim_state()
            except NotImplementedError:
                state = None
            if state is not None:
                return _rebuilt_env, (*construction, state)
        return super().__reduce_ex__(protocol)


def _rebuilt_env(constructor, kwargs: dict, state: dict) -> SimulatorSnapshots:
    """An env built by ``constructor(**kwargs)`` whose simulators continue from ``state`` (``sim_state``)."""
    env = constructor(**kwargs)
    env.remember_construction(constructor, kwargs)
    env.load_sim_state(state)
    return env
