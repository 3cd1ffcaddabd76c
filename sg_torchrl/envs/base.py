"""``SafeEnv``: the one TorchRL base class behind every sg_torchrl task.

A safe environment is a constrained MDP: each step yields a reward *and* a cost, and an agent
must keep its expected episodic cost under a limit (Safety-Gymnasium paper, section 3). The base
class owns everything tasks share:

* ``N`` simulators stepped in one process (``batch_size=[N]``), so the TorchRL per-call overhead
  and the policy forward are paid once per batch, not once per simulator;
* the TensorDict layout: ``observation``; ``reward``, ``cost`` of shape ``(N, 1)`` in the same
  dtype; a ``cost_info`` sub-TensorDict with one ``(N, 1)`` entry per constraint so users can see
  *which* constraint fired; ``terminated`` / ``truncated`` / ``done``;
* partial resets through the ``"_reset"`` mask, the episode step counter and time-limit
  truncation;
* seeding with one generator per simulator (``SeedSequence(seed).spawn``: the ``simulators`` rule
  of :mod:`sg_torchrl.seeding`), so simulator ``i`` with seed ``s`` produces the same trajectory
  whatever ``N`` is; a list of seeds seeds blocks of simulators (``seed`` of :class:`SafeEnv`);
* action validation (shape, finiteness) with errors that name the problem, clipping to the
  action bounds as the reference does, and isolation of a diverged simulator or one whose reward
  or cost is not finite (it is reset and reported ``truncated``, the rest of the batch carries on).
* simulator snapshots and copies (:mod:`sg_torchrl.envs.snapshots`), and the step as numpy arrays
  for the façades (:mod:`sg_torchrl.envs.numpy_step`).

Where ``cost`` is declared
--------------------------
``cost`` and ``cost_info`` live in the **observation spec**, not the reward spec. A second reward
key makes ``env.reward_key`` raise and breaks every transform that reads it (``FrameSkipTransform``,
``UnsqueezeTransform``, ...), whereas observation entries flow through collectors, ``StepCounter``,
``VecNorm`` (which only touches its ``in_keys``) and ``check_env_specs`` untouched. It has the same
shape and dtype as ``reward``, so the same ``GAE`` code path estimates cost advantages
(``GAE.set_keys(reward="cost", ...)``). Use :class:`sg_torchrl.envs.transforms.EpisodeSum` for
per-episode cost sums: TorchRL's ``RewardSum`` only looks in the reward spec.

Subclasses implement the numpy hooks ``_reset_sims``, ``_advance``, ``_observe``,
``_compute_reward``, ``_compute_cost`` and, if the task can end early, ``_compute_terminated``.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from sg_torchrl.envs.numpy_step import NumpyStepInterface
from sg_torchrl.envs import snapshots
from sg_torchrl.envs.snapshots import SimulatorSnapshots
from sg_torchrl.envs.step_hooks import StepHooks, numpy_faced, step_hook
from sg_torchrl.envs.transforms import RewardSpec
from sg_torchrl.seeding import block_seeds, numpy_generators

#: Envs pickled before the snapshot code had a module of its own name their rebuild function here.
_rebuilt_env = snapshots._rebuilt_env

__all__ = ["SafeEnv", "CostMode", "FLOAT32_MAX", "block_seeds", "check_num_envs", "reject_complex_action"]

CostMode = Literal["indicator", "raw"]

FLOAT32_MAX = float(np.finfo(np.float32).max)  # the largest value an emitted reward or cost can hold


def check_num_envs(num_envs: object) -> None:
    """Raise ``ValueError`` unless ``num_envs`` is a positive integer (tasks call it before building simulators)."""
    if not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")


def _magnitude(reward: np.ndarray, costs: dict[str, np.ndarray]) -> float:
    """The sum of the absolute rewards and raw costs of the whole batch (NaN when one is NaN).

    One-element arrays (one simulator, one agent) are read as Python floats: the same float64
    additions, without a numpy reduction per array.
    """
    magnitude = abs(reward.item()) if reward.size == 1 else np.add.reduce(np.abs(reward), axis=None)
    for value in costs.values():
        magnitude += abs(value.item()) if value.size == 1 else np.add.reduce(np.abs(value), axis=None)
    return magnitude


def reject_complex_action(env: object, action: torch.Tensor | np.ndarray) -> None:
    """Raise ``TypeError`` for a complex-valued action, naming its dtype.

    Casting it to the float64 control would keep the real part and drop the imaginary one with only a
    numpy ``ComplexWarning``: a policy bug that should stop the step, not steer the robot.
    """
    complex_valued = action.is_complex() if isinstance(action, torch.Tensor) else np.iscomplexobj(action)
    if complex_valued:
        raise TypeError(f"{type(env).__name__}: action has complex dtype {action.dtype}; actions must be real "
                        f"(a floating-point tensor)")


class SafeEnv(StepHooks, NumpyStepInterface, SimulatorSnapshots, EnvBase, abc.ABC):
    """Batched constrained-MDP environment emitting ``reward`` and ``cost``.

    Args:
        num_envs: number of simulators ``N`` stepped by this env (``batch_size=[N]``).
        observation_dim: length of the flat observation vector.
        action_low / action_high: per-dimension action bounds; actions outside are clipped.
        constraint_names: names of the ``cost_info`` entries, one per constraint. May be empty
            (a task without constraints, e.g. Safety-Gymnasium's level-0 navigation tasks): then
            ``cost_info`` is an empty sub-TensorDict and ``cost`` is always 0.
        max_episode_steps: episodes are truncated after this many steps.
        frame_skip: physics steps per env step (done inside the env, see ``_has_frame_skip``).
        cost_mode: ``"indicator"`` (default, Safety-Gymnasium's ``constrain_indicator``): every
            per-constraint cost and their sum become 1.0 if positive else 0.0, so ``cost`` is in
            {0, 1} and two simultaneous violations still cost 1. ``"raw"``: the continuous values.
        device: device of the emitted tensors (simulation runs on the CPU).
        seed: seed for the per-simulator generators; ``None`` draws one from the OS. A sequence of
            ``K`` seeds (``K`` dividing ``num_envs``) seeds ``K`` equal contiguous blocks of simulators,
            block ``k`` exactly as an env of ``num_envs // K`` simulators with seed ``seeds[k]``: one
            batched env for the ``K`` runs of a seed group (:func:`block_seeds`).

    Keys emitted after a step (``td["next"]``): ``observation`` ``(N, obs_dim)`` float32,
    ``reward`` and ``cost`` ``(N, 1)`` float32, ``("cost_info", name)`` ``(N, 1)`` float32,
    ``terminated``/``truncated``/``done`` ``(N, 1)`` bool.
    """

    # Frame skipping happens inside the env: without this flag TorchRL wraps any env with a
    # ``frame_skip`` attribute in a FrameSkipTransform, skipping frames twice.
    _has_frame_skip = True
    _batch_locked = True

    def __init__(
        self,
        *,
        num_envs: int,
        observation_dim: int,
        action_low: np.ndarray,
        action_high: np.ndarray,
        constraint_names: Sequence[str],
        max_episode_steps: int,
        frame_skip: int = 1,
        cost_mode: CostMode = "indicator",
        device: torch.device | str = "cpu",
        seed: int | Sequence[int] | None = None,
    ) -> None:
        check_num_envs(num_envs)
        if max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
        if frame_skip < 1:
            raise ValueError(f"frame_skip must be >= 1, got {frame_skip}")
        if cost_mode not in ("indicator", "raw"):
            raise ValueError(f"cost_mode must be 'indicator' or 'raw', got {cost_mode!r}")
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.num_envs = num_envs
        self.frame_skip = frame_skip
        self.max_episode_steps = int(max_episode_steps)
        self.cost_mode: CostMode = cost_mode
        self.constraint_names = tuple(constraint_names)
        self._action_low = np.asarray(action_low, dtype=np.float64)
        self._action_high = np.asarray(action_high, dtype=np.float64)
        # The bounds as (1, act_dim) rows and the step increment as an array: a ufunc whose operands
        # broadcast from another rank or are Python scalars costs about a microsecond more per call.
        self._clip_low, self._clip_high = self._action_low[None], self._action_high[None]
        self._elapsed = np.zeros(num_envs, dtype=np.int64)
        self._one_step = np.ones(1, dtype=np.int64)
        self._cpu = torch.device("cpu")
        self.physics_errors = 0  # simulators isolated and reset (diverged, or non-finite reward/cost), since construction
        self._make_specs(observation_dim)
        self._rngs: list[np.random.Generator] = []
        self._set_seed(seed)

    # ------------------------------------------------------------------ specs
    def _make_specs(self, observation_dim: int) -> None:
        n = self.num_envs
        scalar = dict(shape=(n, 1), dtype=torch.float32, device=self.device)
        self.observation_spec = Composite(
            observation=Unbounded(shape=(n, observation_dim), dtype=torch.float32, device=self.device),
            cost=Unbounded(**scalar),
            cost_info=Composite(
                {name: Unbounded(**scalar) for name in self.constraint_names}, shape=(n,), device=self.device
            ),
            shape=(n,),
            device=self.device,
        )
        self.action_spec = Bounded(
            low=torch.as_tensor(self._action_low, dtype=torch.float32).expand(n, -1).clone(),
            high=torch.as_tensor(self._action_high, dtype=torch.float32).expand(n, -1).clone(),
            shape=(n, len(self._action_low)),
            dtype=torch.float32,
            device=self.device,
        )
        self.full_reward_spec = RewardSpec(reward=Unbounded(**scalar), shape=(n,), device=self.device)
        flag = dict(n=2, shape=(n, 1), dtype=torch.bool, device=self.device)
        self.full_done_spec = Composite(
            done=Categorical(**flag), terminated=Categorical(**flag), truncated=Categorical(**flag),
            shape=(n,), device=self.device,
        )

    @property
    def observation_dim(self) -> int:
        """Length of the flat ``observation`` vector (an env that emits none, pixels only, raises)."""
        if "observation" not in self.observation_spec.keys():
            raise ValueError(f"{type(self).__name__} emits no flat 'observation' vector (its observations are "
                             f"{sorted(k for k in self.observation_spec.keys() if k not in ('cost', 'cost_info'))})")
        return int(self.observation_spec["observation"].shape[-1])

    @property
    def action_dim(self) -> int:
        return len(self._action_low)

    # ------------------------------------------------------------------ hooks for tasks
    @abc.abstractmethod
    def _reset_sims(self, indices: np.ndarray) -> None:
        """Reset the simulators ``indices``, drawing randomness from ``self._rngs[i]`` only."""

    @abc.abstractmethod
    @step_hook
    def _advance(self, action: np.ndarray) -> None:
        """Apply the (clipped) ``(N, act_dim)`` action and step every simulator ``frame_skip`` times."""

    @abc.abstractmethod
    @step_hook
    def _observe(self) -> np.ndarray:
        """Current observations, ``(N, obs_dim)`` (may be a buffer the next call reuses: it is copied)."""

    @abc.abstractmethod
    @step_hook
    def _compute_reward(self, action: np.ndarray) -> np.ndarray:
        """Reward of the step just taken, ``(N,)``; ``action`` is the action as given."""

    @abc.abstractmethod
    @step_hook
    def _compute_cost(self) -> dict[str, np.ndarray]:
        """Raw non-negative cost of each constraint for the step just taken, each ``(N,)``."""

    @step_hook
    def _compute_terminated(self) -> np.ndarray:
        """Which simulators reached a terminal state, ``(N,)`` bool. Default: never."""
        return np.zeros(self.num_envs, dtype=bool)

    @step_hook
    def _before_step(self) -> None:
        """Record anything the reward or cost needs from the pre-step state (e.g. positions)."""

    def _diverged(self, observation: np.ndarray) -> np.ndarray:
        """Which simulators hold a non-finite state after stepping, ``(N,)`` bool.

        A subclass that adds a condition here must add it to :meth:`_fault_free` too.
        """
        return ~np.isfinite(observation).all(axis=1)

    @step_hook
    def _fault_free(self, observation: np.ndarray, reward: np.ndarray, costs: dict[str, np.ndarray]) -> bool:
        """A screen before :meth:`_diverged` and :meth:`_nonfinite_outcome`: ``True`` only when neither
        would flag any simulator, so the step can skip building their ``(N,)`` masks.

        Why: on one simulator those masks cost more than the physics of a small robot. Here a
        finite sum of the whole observation proves every entry finite (NaN and inf propagate; a
        sum that overflows only sends the step to the exact test), and the outcome test is
        :meth:`_nonfinite_outcome`'s own whole-batch magnitude.
        """
        return math.isfinite(np.add.reduce(observation, axis=None)) and _magnitude(reward, costs) <= FLOAT32_MAX

    def _nonfinite_outcome(self, reward: np.ndarray, costs: dict[str, np.ndarray]) -> np.ndarray:
        """Which simulators' reward or cost would be emitted non-finite, ``(N,)`` bool.

        A finite state can still give a non-finite outcome: the velocity tasks price the action as
        given, so an action of 1e20 (finite, hence accepted) costs 1e39, which is ``-inf`` once cast
        to the emitted float32. Such a transition is no more usable than a diverged one, so
        :meth:`_transition_arrays` isolates it the same way (truncated, counted in
        :attr:`physics_errors`, reward and cost zeroed). ``reward`` and the raw per-constraint
        ``costs`` may be ``(N,)`` or ``(N, A)``; the raw costs are checked, not their indicators
        (which turn ``inf`` into 1 and NaN into 0, hiding the fault).

        The test is that a simulator's absolute rewards and costs sum to at most float32's largest
        value (NaN fails every comparison): then every emitted value, the raw cost total included,
        is finite. One sum over the whole batch decides the common all-finite case (about 3 us, the
        per-step price of this check); only when it fails is the sum taken per simulator.
        """
        if _magnitude(reward, costs) <= FLOAT32_MAX:
            return np.zeros(self.num_envs, dtype=bool)
        n = self.num_envs
        per_sim = np.abs(np.reshape(reward, (n, -1))).sum(axis=1)
        for value in costs.values():
            per_sim += np.abs(np.reshape(value, (n, -1))).sum(axis=1)
        return ~(per_sim <= FLOAT32_MAX)

    # ------------------------------------------------------------------ TorchRL API
    def _set_seed(self, seed: int | Sequence[int] | None) -> None:
        # Child i depends only on (seed, i): simulator i replays identically whatever N is.
        self._rngs = numpy_generators(seed, self.num_envs)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is None:
            indices = np.arange(self.num_envs)
        else:
            indices = np.flatnonzero(mask.reshape(self.num_envs).cpu().numpy())
        if len(indices):
            self._reset_sims(indices)
            self._elapsed[indices] = 0
        observation = self._observe()
        zeros = np.zeros(self.num_envs)
        return self._pack(observation, reward=None, costs={name: zeros for name in self.constraint_names},
                          terminated=np.zeros(self.num_envs, dtype=bool),
                          truncated=np.zeros(self.num_envs, dtype=bool))

    @numpy_faced("flat")
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self._validated_action(tensordict.get("action"))
        return self._pack(*self._transition_arrays(action))

    @step_hook
    def _transition_arrays(self, action: np.ndarray) -> tuple:
        """One batched step on numpy arrays, the body of ``_step`` without TensorDicts.

        ``action`` is the validated ``(N, act_dim)`` float64 action. Returns ``(observation,
        reward, costs, terminated, truncated)`` with raw per-constraint ``costs`` (aggregated by
        :meth:`_pack`). The gymnasium façade calls this directly to skip TensorDict overhead.
        """
        clipped = np.minimum(np.maximum(action, self._clip_low), self._clip_high)  # np.clip, cheaper
        self._before_step()
        self._advance(clipped)
        observation = self._observe()
        reward = self._compute_reward(action)
        costs = self._compute_cost()
        terminated = self._compute_terminated()
        np.add(self._elapsed, self._one_step, out=self._elapsed)  # in place: assigning an attribute of an nn.Module costs microseconds
        truncated = self._elapsed >= self.max_episode_steps
        if self._fault_free(observation, reward, costs):  # the common case, decided without (N,) masks
            return observation, reward, costs, terminated, truncated
        diverged = self._diverged(observation) | self._nonfinite_outcome(reward, costs)
        if diverged.any():
            return self._isolate(diverged, observation, reward, costs, terminated, truncated)
        return observation, reward, costs, terminated, truncated

    def _step_proc_data(self, next_tensordict_out: TensorDictBase) -> TensorDictBase:
        # EnvBase reshapes the reward to its spec and fills in missing done flags here, walking the
        # specs on every step. ``_pack`` already emits the reward and every done flag with their
        # declared shapes, so that walk is skipped unless type checks were requested.
        if self.run_type_checks:
            return super()._step_proc_data(next_tensordict_out)
        return next_tensordict_out

    def _reset_proc_data(self, tensordict: TensorDictBase | None, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # EnvBase completes missing done flags, checks that no reset simulator is done and merges
        # the reset rows into the input through ``TensorDict.where``: together about a third of a
        # one-simulator reset. ``_reset`` emits every done flag, all False, with the declared
        # shapes, so only the merge is needed; it is done here with one ``torch.where`` per entry
        # and the same result as TorchRL's (entries missing on one side read 0 in those rows).
        if self.run_type_checks or tensordict is None:
            return super()._reset_proc_data(tensordict, tensordict_reset)
        mask = tensordict.get("_reset", None)
        if mask is None or bool(mask.all()):
            return super()._reset_proc_data(tensordict, tensordict_reset)
        entries = {}
        for source in (tensordict_reset, tensordict):
            for key, value in source.items(include_nested=True, leaves_only=True):
                if not isinstance(value, torch.Tensor) or value.device != mask.device:
                    return super()._reset_proc_data(tensordict, tensordict_reset)  # the general path
                entries.setdefault(key, None)
        del tensordict["_reset"], entries["_reset"]
        reset_rows = mask.reshape(self.num_envs)
        for key in entries:
            new, old = tensordict_reset.get(key, None), tensordict.get(key, None)
            if new is None:
                new = torch.zeros_like(old)
            elif old is None or old.shape != new.shape or old.dtype != new.dtype:
                old = torch.zeros_like(new)
            rows = reset_rows.reshape(self.num_envs, *([1] * (new.ndim - 1)))
            tensordict.set(key, torch.where(rows, new, old))
        return tensordict

    # ------------------------------------------------------------------ helpers
    def _validated_action(self, action: torch.Tensor | None) -> np.ndarray:
        expected = (self.num_envs, self.action_dim)
        if action is None:
            raise KeyError("the input TensorDict has no 'action' entry")
        if tuple(action.shape) != expected:
            raise ValueError(
                f"{type(self).__name__}: action has shape {tuple(action.shape)}, expected {expected} "
                f"(num_envs={self.num_envs}, action_dim={self.action_dim})"
            )
        reject_complex_action(self, action)
        array = action.detach().cpu().numpy().astype(np.float64)
        if not np.isfinite(array).all():
            bad = np.flatnonzero(~np.isfinite(array).all(axis=1)).tolist()
            raise ValueError(f"{type(self).__name__}: non-finite action (NaN or inf) for simulators {bad}")
        return array

    def _isolate(self, diverged, observation, reward, costs, terminated, truncated):
        """Reset diverged simulators and report them truncated with zero reward and cost.

        Rewards and costs may carry trailing dimensions (one value per agent, ``(N, A)``).
        """
        self.physics_errors += int(diverged.sum())
        indices = np.flatnonzero(diverged)
        self._reset_sims(indices)
        self._elapsed[indices] = 0

        def zeroed(value: np.ndarray) -> np.ndarray:
            return np.where(diverged.reshape(-1, *([1] * (np.ndim(value) - 1))), 0.0, value)

        observation = zeroed(observation)
        reward = zeroed(reward)
        costs = {name: zeroed(value) for name, value in costs.items()}
        return observation, reward, costs, terminated & ~diverged, truncated | diverged

    def _observation_entries(self, observation: np.ndarray) -> dict[str, torch.Tensor]:
        """The observation entries of an output TensorDict, fresh tensors with the declared shapes.

        Default: the flat ``observation`` vector, float32. Envs with other observations (pixels,
        :mod:`sg_torchrl.envs.vision`) override it; the vector is still computed every step (it
        also tells diverged simulators apart).
        """
        return {"observation": torch.from_numpy(np.array(observation, dtype=np.float32).reshape(self.num_envs, -1))}

    @step_hook
    def _aggregate_cost(self, costs: dict[str, np.ndarray]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The total cost and the ``cost_info`` entries for raw per-constraint ``costs``, each ``(N,)``
        (or ``(N, A)``, one value per agent: then per agent), under :attr:`cost_mode`."""
        if self.cost_mode == "indicator" and len(costs) == 1:
            # One constraint: 0 + v > 0 is v > 0 for every v (signed zeros and NaN included), so the total's
            # indicator is the constraint's own, without the sum.
            (name, value), = costs.items()
            indicator = (value > 0).astype(np.float32)
            return indicator, {name: indicator.copy()}
        shape = np.shape(next(iter(costs.values()))) if costs else (self.num_envs,)
        total = sum(costs.values(), np.zeros(shape))
        if self.cost_mode == "indicator":
            return (total > 0).astype(np.float32), {k: (v > 0).astype(np.float32) for k, v in costs.items()}
        return total, costs

    def _pack(self, observation, reward, costs, terminated, truncated) -> TensorDictBase:
        """The output TensorDict. Every tensor in it is a fresh copy: collectors and rollouts keep
        references to emitted tensors, so nothing the env writes to later may be shared with them."""
        cost, cost_info = self._aggregate_cost(costs)
        n = self.num_envs

        def fresh(array: np.ndarray, dtype: type) -> torch.Tensor:
            return torch.from_numpy(np.array(array, dtype=dtype).reshape(n, -1))  # np.array copies

        source = {
            **self._observation_entries(observation),
            "cost": fresh(cost, np.float32),
            "cost_info": {name: fresh(value, np.float32) for name, value in cost_info.items()},
            "terminated": fresh(terminated, np.bool_),
            "truncated": fresh(truncated, np.bool_),
            "done": fresh(terminated | truncated, np.bool_),
        }
        if reward is not None:
            source["reward"] = fresh(reward, np.float32)
        # The entries are built here with the declared shapes, dtypes and device, so TensorDict's
        # per-entry validation (a sizeable share of the per-step cost) is skipped.
        out = TensorDict._new_unsafe(source, batch_size=self.batch_size, device=self._cpu)
        return out if self.device is None or self.device.type == "cpu" else out.to(self.device)

