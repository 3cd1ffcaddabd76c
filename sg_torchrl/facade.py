"""What the gymnasium and PettingZoo façades (:mod:`sg_torchrl.gym`, :mod:`sg_torchrl.pettingzoo`) share:
one simulator of an sg_torchrl env, its rendering, copies and call-order checks."""

from __future__ import annotations

import copy
from typing import Any

import gymnasium
import numpy as np

from sg_torchrl.render_modes import render_frames

__all__ = ["EpisodeEndedError", "SimulatorFacade"]


class EpisodeEndedError(gymnasium.error.ResetNeeded, AssertionError):
    """``step`` was called before ``reset`` or after the episode ended.

    Also an ``AssertionError``, so code written for Safety-Gymnasium (which asserts) still catches it.
    """


class SimulatorFacade:
    """What the gymnasium and PettingZoo façades share: one simulator ``_env`` of ``env_id``, built from
    ``_options``, with its frame source ``_frames`` (``None`` without a render mode) and ``_closed`` flag."""

    @property
    def torchrl_env(self):
        """The wrapped TorchRL env (one simulator)."""
        return self._env

    def render(self) -> np.ndarray | list[np.ndarray] | None:
        """The frame(s) of :attr:`render_mode` (:mod:`sg_torchrl.render_modes`): an RGB ``(H, W, 3)``
        ``uint8`` or depth ``(H, W)`` ``float32`` array, a list of them (``*_list``), or ``None``."""
        self._check_open()
        return render_frames(self._frames)

    def _release(self) -> None:
        """``close()``'s shared part: mark closed, close the window and the simulator."""
        self._closed = True
        if self._frames is not None:
            self._frames.close()
        self._env.close(raise_if_closed=False)

    def _clone(self, memo: dict):
        """A new façade with this one's id and options whose simulator continues from this one's
        (:meth:`~sg_torchrl.envs.base.SafeEnv.sim_state` loaded into the copy)."""
        self._check_open()
        if not hasattr(self._env, "sim_state"):
            raise TypeError(f"{self.env_id}: {type(self._env).__name__} cannot snapshot its simulator")
        clone = type(self)(self.env_id, render_mode=self.render_mode, **copy.deepcopy(self._options, memo))
        memo[id(self)] = clone
        clone._env.load_sim_state(copy.deepcopy(self._env.sim_state(), memo))
        return clone

    def _check_open(self) -> None:
        if self._closed:
            raise gymnasium.error.ClosedEnvironmentError(f"{self.env_id}: the env is closed")

    def _check_reset_options(self, options: Any) -> None:
        self._check_open()
        if options is not None and not isinstance(options, dict):
            raise TypeError(f"{self.env_id}: reset options must be a dict or None, got {type(options).__name__}")

    def _raise_episode_ended(self) -> None:
        """``step`` before ``reset`` or after the episode ended (or on a closed env: that error)."""
        self._check_open()
        raise EpisodeEndedError(f"{self.env_id}: call reset() before step(): the episode has not started or has "
                                "ended (terminated or truncated)")

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.env_id!r})"
