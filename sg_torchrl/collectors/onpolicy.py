"""A lean on-policy rollout collector with exact checkpoint/resume.

TorchRL's :class:`~torchrl.collectors.Collector` works with every sg_torchrl env (see the tests),
and is the right tool for replay-buffer pipelines. The on-policy trainer needs two things it does
not expose publicly: the *carry* (the TensorDict the next step starts from, which after an
auto-reset already holds freshly reset observations) for bit-exact resume, and the lowest possible
per-step overhead on 2-core machines (collection time is pure overhead for small MLP policies).
:class:`RolloutCollector` is that: ``steps`` calls of ``policy`` then ``env.step_and_maybe_reset``,
written into a ``(N, steps)`` TensorDict in TorchRL's layout (time is the last batch dim, named
``"time"``), with :meth:`state_dict` / :meth:`load_state_dict` covering the carry and the
simulators.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from sg_torchrl.envs.base import SafeEnv

__all__ = ["RolloutCollector"]


def _base_env(env: EnvBase) -> EnvBase:
    while hasattr(env, "base_env"):
        env = env.base_env
    return env


class RolloutCollector:
    """Collect fixed-length on-policy batches from a batched env.

    Args:
        env: a batched env (a :class:`SafeEnv`, possibly wrapped in a ``TransformedEnv``).
        policy: writes ``"action"`` (and whatever else the loss needs, e.g. ``loc``, ``scale``,
            ``action_log_prob``) from the carry.
        steps: env steps per simulator in each batch, so a batch holds ``N * steps`` transitions.
        exploration: exploration type used while collecting (``RANDOM`` samples the policy).
    """

    def __init__(
        self,
        env: EnvBase,
        policy: TensorDictModuleBase,
        steps: int,
        *,
        exploration: ExplorationType = ExplorationType.RANDOM,
    ) -> None:
        if steps < 1:
            raise ValueError(f"steps per batch must be >= 1, got {steps}")
        self.env = env
        self.policy = policy
        self.steps = steps
        self.exploration = exploration
        self.frames = 0
        self._carry: TensorDictBase = env.reset()

    @property
    def frames_per_batch(self) -> int:
        return self.steps * int(self.env.batch_size.numel())

    @torch.no_grad()
    def collect(self) -> TensorDictBase:
        """Run ``steps`` env steps and return the ``(N, steps)`` batch of transitions."""
        carry, env, policy = self._carry, self.env, self.policy
        frames = []
        with set_exploration_type(self.exploration):
            for _ in range(self.steps):
                carry = policy(carry)
                transition, carry = env.step_and_maybe_reset(carry)
                frames.append(transition)
                self.after_step(transition)
        self._carry = carry
        self.frames += self.frames_per_batch
        batch = torch.stack(frames, dim=len(env.batch_size))
        batch.refine_names(*([None] * len(env.batch_size)), "time")
        return batch

    def after_step(self, transition: TensorDictBase) -> None:
        """Called with every step's transitions as they are collected; nothing here (a subclass's hook: the
        off-policy engine fills its replay buffers and takes its gradient steps there)."""

    # ------------------------------------------------------------------ checkpointing
    def state_dict(self) -> dict[str, Any]:
        """The carry, the frame count and, for sg_torchrl envs, the exact simulator state.

        The carry is a TensorDict and the simulator state holds numpy arrays and bit-generator
        states; ``sg-train`` checkpoints encode both as tensors and plain data
        (:mod:`sg_torchrl.train.checkpoint`), so they load with ``torch.load(weights_only=True)``.
        """
        base = _base_env(self.env)
        return {
            "carry": self._carry.clone(),
            "frames": self.frames,
            "sims": base.sim_state() if isinstance(base, SafeEnv) else None,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._carry = state["carry"].clone()
        self.frames = int(state["frames"])
        if state["sims"] is not None:
            _base_env(self.env).load_sim_state(state["sims"])
