"""Finished-episode statistics (return, cost, length, per-constraint cost) from collected batches.

A collector hands out fixed-size batches, and an episode usually spans several of them. SafePO
logs statistics of *finished* episodes (``Metrics/EpRet``, ``Metrics/EpCost``, ``Metrics/EpLen``
as 50-episode moving averages), so :class:`EpisodeStats` carries per-env running sums across batch
boundaries and emits one record at every ``done``.

Layout assumptions (what :meth:`EpisodeStats.update` accepts):

* ``[N, T]`` -- TorchRL's ``Collector`` output for an env with ``batch_size=[N]`` and
  ``split_trajs=False``: env index first, time last (dim names ``[None, "time"]``).
* ``[T]`` -- a single unbatched env.
* Any ``[*B, T]``; if a batch dim is named ``"time"`` it is used as the time dim, otherwise the
  last one is. The other dims are flattened into the env index, so they must keep the same size
  and order from one call to the next (they do for a given collector).

Values are read from the ``("next", ...)`` entries (the step's outcome), and every env is assumed
to start a fresh episode at the first batch (collectors reset their env when they start). Do not
use ``reset_at_each_iter=True`` collectors with this class: their resets are not marked ``done``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

__all__ = ["EpisodeStats"]

_METRIC_NAMES = {"return": "Metrics/EpRet", "cost": "Metrics/EpCost", "length": "Metrics/EpLen"}


class EpisodeStats:
    """Accumulate per-env episode sums over collected batches; record each finished episode.

    Args:
        reward_key: per-step reward entry. Default ``("next", "reward")``.
        cost_key: per-step cost entry, or ``None`` to track no cost. Default ``("next", "cost")``.
        done_key: end-of-episode flag. Default ``("next", "done")``.
        cost_info_key: sub-TensorDict of per-constraint costs, summed per leaf and reported as
            ``"cost_info/<name>"`` (nested names joined with ``/``). Ignored when absent from the
            first batch, or when ``None``. Default ``("next", "cost_info")``.
        agent_dim: for multi-agent groups, e.g. ``("next", "agents", "reward")`` of shape
            ``(*B, T, n_agents, 1)``: the agent dim (``-2`` in TorchRL's MARL layout), reduced by a
            mean for rewards and costs and by ``any`` for a per-agent done. Only entries with more
            dims than ``batch_dims + 1`` are reduced, so an env-level ``("next", "done")`` of shape
            ``(*B, T, 1)`` is used as is. ``None`` (default): no agent dim.
        history: number of most recent finished episodes retained for :meth:`window`.

    Sums are accumulated in float64 and reported as float64 (``length`` as int64).
    """

    def __init__(
        self,
        *,
        reward_key: NestedKey = ("next", "reward"),
        cost_key: NestedKey | None = ("next", "cost"),
        done_key: NestedKey = ("next", "done"),
        cost_info_key: NestedKey | None = ("next", "cost_info"),
        agent_dim: int | None = None,
        history: int = 1000,
    ):
        if history < 1:
            raise ValueError(f"history must be >= 1, got {history}")
        self.reward_key = reward_key
        self.cost_key = cost_key
        self.done_key = done_key
        self.cost_info_key = cost_info_key
        self.agent_dim = agent_dim
        self.history = history
        self.reset()

    # ------------------------------------------------------------------ state

    def reset(self) -> None:
        """Forget everything: running sums, pending and retained episodes, the episode count."""
        self._channels: list[str] | None = None  # "return", ["cost"], ["cost_info/*"], "length"
        self._cost_info_leaves: list[NestedKey] = []
        self._running: torch.Tensor | None = None  # (C, num_envs) float64
        self._pending: list[torch.Tensor] = []  # (C, E) per update, not yet popped
        self._recent: torch.Tensor | None = None  # (C, <= history), oldest first
        self._num_episodes = 0

    @property
    def num_episodes(self) -> int:
        """Episodes finished since construction (or since the restored checkpoint's start)."""
        return self._num_episodes

    @property
    def num_envs(self) -> int | None:
        """Number of envs tracked (known after the first :meth:`update`)."""
        return None if self._running is None else self._running.shape[1]

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume mid-episode: running sums, pending and retained episodes."""
        return {
            "channels": None if self._channels is None else list(self._channels),
            "cost_info_leaves": list(self._cost_info_leaves),
            "running": None if self._running is None else self._running.clone(),
            "pending": self._cat_pending(),
            "recent": None if self._recent is None else self._recent.clone(),
            "num_episodes": self._num_episodes,
        }

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        self.reset()
        channels = state_dict["channels"]
        self._channels = None if channels is None else list(channels)
        self._cost_info_leaves = [
            tuple(k) if isinstance(k, list) else k for k in state_dict["cost_info_leaves"]
        ]
        running = state_dict["running"]
        self._running = None if running is None else running.clone().to(torch.float64)
        pending = state_dict["pending"]
        if pending is not None and pending.shape[-1] > 0:
            self._pending = [pending.clone()]
        recent = state_dict["recent"]
        self._recent = None if recent is None else recent.clone()
        self._num_episodes = int(state_dict["num_episodes"])

    # ------------------------------------------------------------------ update

    def update(self, batch: TensorDictBase) -> None:
        """Add a collected batch (``[N, T]``, ``[T]`` or ``[*B, T]``, see the module docstring)."""
        time_dim = self._time_dim(batch)
        if self._channels is None:
            self._init_channels(batch)
        keys: list[NestedKey] = [self.reward_key]
        if self.cost_key is not None:
            keys.append(self.cost_key)
        keys.extend(self._cost_info_leaves)

        done = self._env_level(batch.get(self.done_key), batch, time_dim, reduce="any")
        num_envs, steps = done.shape
        if self._running is None:
            self._running = torch.zeros(len(self._channels), num_envs, dtype=torch.float64)
        elif self._running.shape[1] != num_envs:
            raise ValueError(
                f"batch holds {num_envs} envs but the running sums track {self._running.shape[1]}"
            )

        # (C, N, T): one channel per tracked quantity, the last one counts steps.
        values = torch.empty(len(self._channels), num_envs, steps, dtype=torch.float64)
        for c, key in enumerate(keys):
            values[c] = self._env_level(batch.get(key), batch, time_dim, reduce="mean")
        values[-1] = 1.0

        # Running sum including the carry from earlier batches; an episode ending at step t whose
        # previous episode ended at step p (same env) sums to cum[t] - cum[p] (carry cancels), or
        # cum[t] if no episode ended earlier in this batch (carry included).
        cum = values.cumsum(-1).add_(self._running.unsqueeze(-1))
        steps_idx = torch.arange(steps)
        last_done = torch.where(done, steps_idx, -1).cummax(-1).values  # (N, T), <= t
        t_end, env = done.T.nonzero(as_tuple=True)  # chronological, then by env index
        if t_end.numel():
            prev = torch.where(t_end > 0, last_done[env, (t_end - 1).clamp(min=0)], -1)
            base = torch.where(prev >= 0, cum[:, env, prev.clamp(min=0)], 0.0)
            finished = cum[:, env, t_end] - base
            self._pending.append(finished)
            self._num_episodes += finished.shape[1]
            recent = finished if self._recent is None else torch.cat([self._recent, finished], 1)
            self._recent = recent[:, -self.history :]
        end = last_done[:, -1]
        base_end = torch.where(end >= 0, cum[:, torch.arange(num_envs), end.clamp(min=0)], 0.0)
        self._running = cum[:, :, -1] - base_end

    # ------------------------------------------------------------------ queries

    def pop_finished(self) -> dict[str, torch.Tensor]:
        """All episodes finished since the last pop, oldest first: one 1-D tensor per statistic.

        Keys: ``"return"``, ``"cost"`` (when ``cost_key`` is set), ``"length"``, and
        ``"cost_info/<name>"`` per constraint.
        """
        finished = self._cat_pending()
        self._pending = []
        if finished is None:
            return {name: self._empty(name) for name in self._default_channels()}
        return self._as_dict(finished)

    def window(self, n: int = 50) -> dict[str, float]:
        """Means over the last ``n`` finished episodes (fewer if fewer finished; ``{}`` if none).

        At most ``history`` episodes are retained.
        """
        if self._recent is None or self._recent.shape[1] == 0:
            return {}
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        last = self._recent[:, -n:]
        return {name: float(v) for name, v in zip(self._channels, last.mean(1), strict=True)}

    def metrics(self, n: int = 50) -> dict[str, float]:
        """:meth:`window` under SafePO's metric names (``Metrics/EpRet``, ``Metrics/EpCost``,
        ``Metrics/EpLen``); ``{}`` until an episode has finished."""
        return {_METRIC_NAMES[k]: v for k, v in self.window(n).items() if k in _METRIC_NAMES}

    # ------------------------------------------------------------------ helpers

    def _default_channels(self) -> list[str]:
        if self._channels is not None:
            return self._channels
        return ["return"] + (["cost"] if self.cost_key is not None else []) + ["length"]

    def _init_channels(self, batch: TensorDictBase) -> None:
        leaves: list[NestedKey] = []
        names: list[str] = []
        info = None if self.cost_info_key is None else batch.get(self.cost_info_key, None)
        if info is not None:
            for leaf in info.keys(include_nested=True, leaves_only=True):
                leaf = (leaf,) if isinstance(leaf, str) else tuple(leaf)
                prefix = self.cost_info_key
                prefix = (prefix,) if isinstance(prefix, str) else tuple(prefix)
                leaves.append(prefix + leaf)
                names.append("cost_info/" + "/".join(leaf))
        self._cost_info_leaves = leaves
        self._channels = (
            ["return"] + (["cost"] if self.cost_key is not None else []) + names + ["length"]
        )

    @staticmethod
    def _time_dim(batch: TensorDictBase) -> int:
        if batch.batch_dims == 0:
            raise ValueError("EpisodeStats.update needs a batch with a time dim, got batch_size []")
        try:
            names = batch.names
        except Exception:  # some tensordict types do not support names
            names = None
        if names and "time" in names:
            return list(names).index("time")
        return batch.batch_dims - 1

    def _env_level(
        self, x: torch.Tensor, batch: TensorDictBase, time_dim: int, reduce: str
    ) -> torch.Tensor:
        """Reduce ``x`` to the batch shape (agent dim, trailing 1), then to ``(envs, T)``."""
        ndim = batch.batch_dims
        if self.agent_dim is not None and x.ndim >= ndim + 2:
            x = x.any(self.agent_dim) if reduce == "any" else x.double().mean(self.agent_dim)
        if x.ndim == ndim + 1 and x.shape[-1] == 1:
            x = x.squeeze(-1)
        if x.shape != batch.batch_size:
            raise ValueError(
                f"entry of shape {tuple(x.shape)} does not reduce to the batch shape "
                f"{tuple(batch.batch_size)} (set agent_dim for per-agent entries)"
            )
        if reduce == "any":
            x = x.bool()
        return x.movedim(time_dim, -1).reshape(-1, batch.batch_size[time_dim])

    def _cat_pending(self) -> torch.Tensor | None:
        if not self._pending:
            return None
        if len(self._pending) > 1:
            self._pending = [torch.cat(self._pending, 1)]
        return self._pending[0].clone()

    def _empty(self, name: str) -> torch.Tensor:
        return torch.zeros(0, dtype=torch.int64 if name == "length" else torch.float64)

    def _as_dict(self, episodes: torch.Tensor) -> dict[str, torch.Tensor]:
        out = dict(zip(self._channels, episodes, strict=True))
        out["length"] = out["length"].round().to(torch.int64)
        return out
