"""One derivation of a run's random streams (:mod:`sg_torchrl.seeding`).

Each purpose's stream is compared with the rule the trainers used before the rules were gathered
in one module, written out here by hand (the golden trajectories and checkpoints depend on them bit
for bit); the purposes are checked to draw different numbers (but for the two coincidences the
module documents); and the package's source is scanned for any other derivation of a stream from
a seed.
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
import torch

from sg_torchrl import seeding
from sg_torchrl.seeding import Purpose

SEEDS = [0, 1, 7, 123, 2**31 - 1]
PACKAGE = Path(seeding.__file__).resolve().parent


def _draws(g: torch.Generator) -> torch.Tensor:
    return torch.cat([torch.rand(8, generator=g), torch.randperm(50, generator=g).float()])


def _numpy_states(children) -> list[list[int]]:
    return [child.generate_state(4).tolist() for child in children]


# ---------------------------------------------------------------------------- (a) the old rules
@pytest.mark.parametrize("seed", SEEDS)
def test_simulators_rule(seed: int) -> None:
    """Simulator ``i`` of an env seeded ``s``: ``default_rng(SeedSequence(s).spawn(N)[i])``."""
    old = np.random.SeedSequence(seed).spawn(6)
    assert _numpy_states(seeding.numpy_seeds(seed, Purpose.SIMULATORS, 6)) == _numpy_states(old)
    assert _numpy_states(seeding.block_seeds(seed, 6)) == _numpy_states(old)
    for new, child in zip(seeding.numpy_generators(seed, 6), old, strict=True):
        np.testing.assert_array_equal(new.random(5), np.random.default_rng(child).random(5))
    assert seeding.env_seed(seed, Purpose.SIMULATORS) == seed == seeding.env_seed(seed)


def test_simulators_rule_for_a_group() -> None:
    """A list of K seeds: block ``k`` of ``N // K`` simulators spawned from ``seeds[k]``."""
    seeds = [3, 0, 11]
    old = [child for s in seeds for child in np.random.SeedSequence(s).spawn(2)]
    assert _numpy_states(seeding.numpy_seeds(seeds, Purpose.SIMULATORS, 6)) == _numpy_states(old)
    with pytest.raises(ValueError, match="equal blocks"):
        seeding.block_seeds(seeds, 7)


@pytest.mark.parametrize("seed", SEEDS)
def test_init_rule(seed: int) -> None:
    """The global torch RNG after ``torch.manual_seed(s)``; :func:`generator` starts where it does."""
    torch.manual_seed(seed)
    old = torch.rand(8)
    assert seeding.seed_torch(seed) is torch.default_generator
    torch.testing.assert_close(torch.rand(8), old, rtol=0, atol=0)
    torch.manual_seed(seed)
    old = torch.rand(8)
    torch.testing.assert_close(torch.rand(8, generator=seeding.generator(seed, Purpose.INIT)), old, rtol=0, atol=0)


@pytest.mark.parametrize("seed", SEEDS)
def test_actions_rule(seed: int) -> None:
    """``Generator().manual_seed(a)`` with ``a`` the first uint64 of ``SeedSequence([s, 1])``."""
    a = int(np.random.SeedSequence([seed, 1]).generate_state(1, dtype=np.uint64)[0])
    assert seeding.action_seed(seed) == a
    old = torch.Generator().manual_seed(a)
    torch.testing.assert_close(_draws(seeding.generator(seed, Purpose.ACTIONS)), _draws(old), rtol=0, atol=0)


def test_actions_rule_pinned() -> None:
    """The action seed of run 0, as a number (it is in every seed group's golden trajectory)."""
    assert seeding.action_seed(0) == 5836529245451711556
    from sg_torchrl.train.seed_group import action_seed  # still importable where it used to live
    assert action_seed is seeding.action_seed


@pytest.mark.parametrize("seed", SEEDS)
def test_minibatches_rule(seed: int) -> None:
    """``Generator().manual_seed(s)`` (the trainer's ``minibatch_rng``, ``SeedShuffler``, a team's round)."""
    old = torch.Generator().manual_seed(seed)
    torch.testing.assert_close(_draws(seeding.generator(seed, Purpose.MINIBATCHES)), _draws(old), rtol=0, atol=0)


def test_minibatch_consumers_use_the_rule() -> None:
    """``SeedShuffler`` and a multi-agent round built without a generator draw the ``minibatches`` streams."""
    from sg_torchrl.modules import make_multi_agent_networks
    from sg_torchrl.train.multi_agent_updates import HAPPOUpdate
    from sg_torchrl.train.fused import SeedShuffler

    order = SeedShuffler([5, 9]).permutation(30)
    for row, seed in zip(order, [5, 9], strict=True):
        torch.testing.assert_close(row, torch.randperm(30, generator=torch.Generator().manual_seed(seed)))
    expected = torch.randperm(4, generator=torch.Generator().manual_seed(0))
    update = HAPPOUpdate(make_multi_agent_networks(3, [1, 1, 1, 1], 2, hidden_sizes=(4,)))
    assert torch.equal(torch.randperm(4, generator=update.shuffler.generators[0]), expected)


@pytest.mark.parametrize("seed", SEEDS)
def test_evaluation_rule(seed: int) -> None:
    """The evaluation env is seeded ``s + 10_000``; its simulators by the simulators' rule."""
    assert seeding.env_seed(seed, Purpose.EVALUATION) == seed + 10_000
    old = np.random.SeedSequence(seed + 10_000).spawn(3)
    assert _numpy_states(seeding.numpy_seeds(seed, Purpose.EVALUATION, 3)) == _numpy_states(old)


def test_wrong_kind_of_stream_is_refused() -> None:
    for purpose in (Purpose.SIMULATORS, Purpose.EVALUATION):
        with pytest.raises(ValueError, match="env"):
            seeding.generator(0, purpose)
    for purpose in (Purpose.INIT, Purpose.ACTIONS, Purpose.MINIBATCHES):
        with pytest.raises(ValueError, match="torch.Generator"):
            seeding.env_seed(0, purpose)
        with pytest.raises(ValueError, match="torch.Generator"):
            seeding.numpy_seeds(0, purpose, 2)
    with pytest.raises(ValueError, match="one run seed"):
        seeding.numpy_seeds([0, 1], Purpose.EVALUATION, 2)
    assert seeding.generator(3, "minibatches").initial_seed() == 3  # a purpose's name is accepted


# ---------------------------------------------------------------------------- (b) distinct streams
@pytest.mark.parametrize("seed", SEEDS)
def test_purposes_draw_different_streams(seed: int) -> None:
    actions = _draws(seeding.generator(seed, Purpose.ACTIONS))
    for purpose in (Purpose.INIT, Purpose.MINIBATCHES):
        assert not torch.equal(actions, _draws(seeding.generator(seed, purpose)))
    simulators = _numpy_states(seeding.numpy_seeds(seed, Purpose.SIMULATORS, 4))
    evaluation = _numpy_states(seeding.numpy_seeds(seed, Purpose.EVALUATION, 4))
    assert simulators != evaluation
    torch_first = _draws(seeding.generator(seed, Purpose.MINIBATCHES))[:8]
    assert not np.isin(np.asarray(simulators).ravel(), (torch_first * 2**32).long().numpy()).any()


def test_documented_coincidences() -> None:
    """``init`` and ``minibatches`` start from one state; evaluation of s is simulators of s + 10_000."""
    torch.testing.assert_close(_draws(seeding.generator(4, Purpose.INIT)),
                               _draws(seeding.generator(4, Purpose.MINIBATCHES)), rtol=0, atol=0)
    assert (_numpy_states(seeding.numpy_seeds(4, Purpose.EVALUATION, 2))
            == _numpy_states(seeding.numpy_seeds(10_004, Purpose.SIMULATORS, 2)))


def test_seeds_draw_different_streams() -> None:
    for purpose in (Purpose.INIT, Purpose.ACTIONS, Purpose.MINIBATCHES):
        streams = [_draws(seeding.generator(seed, purpose)) for seed in SEEDS]
        assert all(not torch.equal(a, b) for i, a in enumerate(streams) for b in streams[i + 1:])


# ---------------------------------------------------------------------------- (c) nowhere else
#: Modules allowed to derive from a seed outside :mod:`sg_torchrl.seeding`, and why.
EXCEPTIONS = {
    # Gymnasium's vector-env contract, kept by the Safety-Gymnasium facade: ``reset(seed=s)`` seeds
    # sub-env ``i`` with ``s + i``. It maps a user's seed onto the facade's envs; no run derives a
    # stream through it.
    "safety_gymnasium/vector/vector_env.py",
}

_SEEDING_CALLS = {"manual_seed", "SeedSequence", "default_rng"}


def _is_seed(name: str) -> bool:
    """``seed``, ``cfg.seed``, ``run_seed``: one seed (a list of ``seeds`` is not offset, only joined or counted)."""
    name = name.lower()
    return name == "seed" or name.endswith("_seed")


def _mentions_seed(node: ast.AST) -> bool:
    return any((isinstance(n, ast.Name) and _is_seed(n.id)) or (isinstance(n, ast.Attribute) and _is_seed(n.attr))
               for n in ast.walk(node))


def derivations(source: str) -> list[tuple[int, str]]:
    """``(line, what)`` for every place ``source`` seeds an RNG or offsets a seed."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if name in _SEEDING_CALLS:
                found.append((node.lineno, name))
            elif name == "seed" and isinstance(func, ast.Attribute):  # np.random.seed, torch.seed, random.seed
                found.append((node.lineno, "seed"))
        elif isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Sub, ast.Mult, ast.BitXor)):
            if _mentions_seed(node.left) or _mentions_seed(node.right):
                found.append((node.lineno, "arithmetic on a seed"))
    return found


def test_scan_finds_the_old_rules() -> None:
    """The scan flags each rule as the trainers used to write it."""
    old = [
        "torch.manual_seed(cfg.seed)",
        "rng = torch.Generator().manual_seed(cfg.seed)",
        "int(np.random.SeedSequence([seed, 1]).generate_state(1, dtype=np.uint64)[0])",
        "np.random.SeedSequence(seed).spawn(num_envs)",
        "rngs = [np.random.default_rng(child) for child in children]",
        "evaluate_policy(env_id, actor, 10, seed=cfg.seed + 10_000)",
        "seeds = [int(seed) + index for index in range(n)]",
        "np.random.seed(0)",
    ]
    for line in old:
        assert derivations(line), line
    assert not derivations("sg_torchrl.make(env_id, seed=seeding.env_seed(cfg.seed, seeding.Purpose.EVALUATION))")


def test_no_other_module_derives_a_stream() -> None:
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE).as_posix()
        if relative == "seeding.py" or relative in EXCEPTIONS:
            continue
        offenders += [f"{relative}:{line}: {what}" for line, what in derivations(path.read_text())]
    assert not offenders, "derive random streams in sg_torchrl.seeding:\n" + "\n".join(offenders)


def test_exceptions_are_still_needed() -> None:
    for relative in EXCEPTIONS:
        assert derivations((PACKAGE / relative).read_text()), f"{relative} no longer derives a seed: drop it"
