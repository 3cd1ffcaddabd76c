"""Every random stream a run draws, derived from its one seed here and nowhere else.

A run (``sg-train --seed s``, or seed ``s`` of a seed group) is reproducible from ``s`` alone: each
source of randomness gets its own stream, derived from ``s`` by a fixed rule for its
:class:`Purpose`. The rules are those the trainers have always used (the golden trajectories and
checkpoints depend on them bit for bit), gathered in one table:

=============== ============================================= ==============================================
purpose         rule                                          consumers
=============== ============================================= ==============================================
``simulators``  env seed ``s``; simulator ``i`` draws from    :class:`~sg_torchrl.envs.base.SafeEnv`
                ``default_rng(SeedSequence(s).spawn(N)[i])``  (``make(..., seed=s)``), the training env of
                (:func:`numpy_seeds`); a list of K seeds:     every trainer; a seed group's batched env
                block ``k`` of ``N // K`` simulators spawned  (``seed=[s0, s1, ...]``)
                from ``seeds[k]`` (:func:`block_seeds`)
``init``        ``torch.manual_seed(s)``, the global torch    the networks' initialisation (every trainer;
                RNG (:func:`seed_torch`), before the networks a group seeds it once per seed before that
                are built; an unstacked run's action noise    seed's networks); the action noise of
                goes on drawing from the same global stream   each seed of the multi-agent engine (a
                                                              group's or ``--seed``'s, whose state is kept
                                                              per seed after its team is built)
``actions``     ``Generator().manual_seed(a)``,               a single-agent seed group's per-seed action
                ``a = SeedSequence([s, 1])``'s first uint64   noise (``OnPolicyGroupTrainer``, ``StackedPolicy``)
                (:func:`action_seed`)
``minibatches`` ``Generator().manual_seed(s)``                a single-agent seed's minibatch order (a seed
                                                              group's ``SeedShuffler``); a multi-agent
                                                              team's round generator (agent orders and
                                                              minibatch shuffles); a multi-agent round or
                                                              agent order built without a generator
                                                              (seed 0)
``replay``      ``Generator().manual_seed(r)``,               an off-policy seed's replay-buffer sampling
                ``r = SeedSequence([s, 2])``'s first uint64   (its TorchRL ``ReplayBuffer``'s generator)
``updates``     ``Generator().manual_seed(u)``,               an off-policy seed's noise in its gradient
                ``u = SeedSequence([s, 3])``'s first uint64   steps (SAC's sampled actions, TD3's target
                                                              smoothing)
``evaluation``  env seed ``s + 10_000`` (:func:`env_seed`),   the deterministic evaluation of every trainer
                its simulators then by the ``simulators``     (``evaluate_policy``), single run or seed of
                rule                                          a group
=============== ============================================= ==============================================

Two coincidences of these rules are kept on purpose (changing either would change every golden
trajectory): ``init`` and ``minibatches`` seed a torch generator with ``s`` alike, so the global RNG
after ``torch.manual_seed(s)`` and the minibatch generator start from the same state (two objects,
so neither advances the other, but the networks' initial weights and the first minibatch order are
made from the same raw numbers); and the
``evaluation`` env of seed ``s`` is seeded as the ``simulators`` of seed ``s + 10_000``.

No other module of the package calls ``torch.manual_seed``, ``np.random.SeedSequence``,
``np.random.default_rng`` or ``torch.Generator().manual_seed`` on a run seed, nor offsets one
(``tests/test_seeding.py`` checks the source).
"""

from __future__ import annotations

import enum
import numbers
from collections.abc import Sequence

import numpy as np
import torch

__all__ = [
    "EVALUATION_OFFSET", "Purpose", "action_seed", "block_seeds", "env_seed", "generator", "numpy_generators",
    "numpy_seeds", "seed_torch",
]

#: What an evaluation env's seed adds to the run seed.
EVALUATION_OFFSET = 10_000


class Purpose(str, enum.Enum):
    """What a random stream is for; each has its own derivation rule (module table)."""

    SIMULATORS = "simulators"
    INIT = "init"
    ACTIONS = "actions"
    MINIBATCHES = "minibatches"
    REPLAY = "replay"
    UPDATES = "updates"
    EVALUATION = "evaluation"


#: Purposes whose stream is a ``torch.Generator`` (:func:`generator`).
_TORCH = (Purpose.INIT, Purpose.ACTIONS, Purpose.MINIBATCHES, Purpose.REPLAY, Purpose.UPDATES)
#: The stream index of each purpose seeded from ``SeedSequence([seed, index])`` (:func:`action_seed` is 1's).
_SPAWNED = {Purpose.ACTIONS: 1, Purpose.REPLAY: 2, Purpose.UPDATES: 3}
#: Purposes whose stream is an env seed, one numpy generator per simulator (:func:`env_seed`).
_ENV = (Purpose.SIMULATORS, Purpose.EVALUATION)


def action_seed(seed: int) -> int:
    """The seed of run ``seed``'s action-noise generator: the first uint64 of ``SeedSequence([seed, 1])``.

    Not ``seed`` itself, which seeds the minibatch-order generator: two ``torch.Generator`` s with one
    seed would draw the same stream.
    """
    return _spawned_seed(seed, _SPAWNED[Purpose.ACTIONS])


def _spawned_seed(seed: int, index: int) -> int:
    return int(np.random.SeedSequence([seed, index]).generate_state(1, dtype=np.uint64)[0])


def generator(seed: int, purpose: Purpose | str) -> torch.Generator:
    """A fresh CPU ``torch.Generator`` drawing the ``purpose`` stream of run ``seed``.

    ``init``: the state the global RNG has after :func:`seed_torch` (``manual_seed(seed)``);
    ``actions``: seeded with :func:`action_seed`; ``minibatches``: seeded with ``seed``; ``replay`` and
    ``updates``: with the first uint64 of ``SeedSequence([seed, 2])`` / ``SeedSequence([seed, 3])``.

    Raises:
        ValueError: ``purpose`` is an env's (``simulators``, ``evaluation``: :func:`env_seed`,
            :func:`numpy_seeds`).
    """
    purpose = Purpose(purpose)
    if purpose in _SPAWNED:
        return torch.Generator().manual_seed(_spawned_seed(seed, _SPAWNED[purpose]))
    if purpose in _TORCH:
        return torch.Generator().manual_seed(int(seed))
    raise ValueError(f"the {purpose.value!r} stream is an env's (env_seed, numpy_seeds), not a torch.Generator")


def seed_torch(seed: int) -> torch.Generator:
    """Seed the global torch RNG for run ``seed`` (the ``init`` stream): ``torch.manual_seed(seed)``.

    Called right before a run's networks are built; what the run then draws from the global RNG
    (an unstacked run's action noise) continues this stream. Returns the default generator.
    """
    return torch.manual_seed(int(seed))


def env_seed(seed: int, purpose: Purpose | str = Purpose.SIMULATORS) -> int:
    """The env seed (``sg_torchrl.make``'s) of run ``seed``'s ``purpose`` env.

    ``simulators`` (the training env): ``seed``; ``evaluation``: ``seed + 10_000``.

    Raises:
        ValueError: ``purpose`` is a torch generator's (:func:`generator`).
    """
    purpose = Purpose(purpose)
    if purpose is Purpose.EVALUATION:
        return int(seed) + EVALUATION_OFFSET
    if purpose is Purpose.SIMULATORS:
        return int(seed)
    raise ValueError(f"the {purpose.value!r} stream is a torch.Generator (generator()), not an env seed")


def block_seeds(seed: int | Sequence[int] | None, num_envs: int) -> list[np.random.SeedSequence]:
    """The seed sequences of ``num_envs`` simulators of an env seeded ``seed``, one per simulator.

    An int (or ``None``: OS entropy) gives ``SeedSequence(seed).spawn(num_envs)``: simulator ``i``
    depends only on ``(seed, i)``. A sequence of ``K`` seeds splits the simulators into ``K`` equal
    contiguous blocks and gives block ``k`` the children of ``seeds[k]`` an env of
    ``num_envs // K`` simulators would give its own, so block ``k`` replays that env exactly (a
    seed group trains ``K`` runs in one batched env this way).

    Raises:
        ValueError: an empty sequence, or one whose length does not divide ``num_envs``.
    """
    if seed is None or isinstance(seed, numbers.Integral):
        return np.random.SeedSequence(seed).spawn(num_envs)
    seeds = [int(s) for s in seed]
    if not seeds or num_envs % len(seeds):
        raise ValueError(f"{len(seeds)} seeds cannot split {num_envs} simulators into equal blocks "
                         f"(num_envs must be a positive multiple of the number of seeds)")
    block = num_envs // len(seeds)
    return [child for s in seeds for child in np.random.SeedSequence(s).spawn(block)]


def numpy_seeds(seed: int | Sequence[int] | None, purpose: Purpose | str, n: int) -> list[np.random.SeedSequence]:
    """The seed sequences of the ``n`` simulators of run ``seed``'s ``purpose`` env (``simulators`` or ``evaluation``).

    ``seed``: a run seed, ``None`` (OS entropy) or, for ``simulators``, a seed group's list of seeds
    (:func:`block_seeds`).
    """
    purpose = Purpose(purpose)
    if purpose not in _ENV:
        raise ValueError(f"the {purpose.value!r} stream is a torch.Generator (generator()), not simulators'")
    if purpose is Purpose.EVALUATION:
        if seed is None or not isinstance(seed, numbers.Integral):
            raise ValueError(f"an evaluation env is seeded from one run seed, got {seed!r}")
        seed = env_seed(seed, purpose)
    return block_seeds(seed, n)


def numpy_generators(seed: int | Sequence[int] | None, n: int) -> list[np.random.Generator]:
    """One ``np.random.Generator`` per simulator of an env seeded ``seed`` (what ``SafeEnv`` draws from).

    Simulator ``i``'s is ``default_rng`` of :func:`block_seeds`'s ``i``-th child; ``seed`` is the env's
    own seed (a run's :func:`env_seed`, ``simulators`` or ``evaluation``).
    """
    return [np.random.default_rng(child) for child in block_seeds(seed, n)]
