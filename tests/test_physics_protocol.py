"""The physics backends implement one protocol, and the one-simulator fast path is a queried capability."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

import sg_torchrl
from sg_torchrl.envs.navigation.env import NavigationEnv
from sg_torchrl.envs.navigation.single import SingleNavigationStep
from sg_torchrl.envs.physics import MujocoBatch
from sg_torchrl.envs.physics_protocol import PhysicsBatch
from sg_torchrl.envs.velocity.robots import load_model
from sg_torchrl.envs.warp_physics import WarpBatch

PROTOCOL_MEMBERS = [name for name in vars(PhysicsBatch) if not name.startswith("_")] + list(
    PhysicsBatch.__annotations__)


@pytest.mark.parametrize("backend", [MujocoBatch, WarpBatch])
def test_both_backends_subclass_the_protocol_and_define_every_method(backend):
    assert PhysicsBatch in backend.__mro__
    for name, member in vars(PhysicsBatch).items():
        if name.startswith("_") or name in ("supports_aliased_single_step", "advance_one", "contact_counts_one"):
            continue
        if callable(member) or isinstance(member, property):
            # The protocol's bodies are "..." (None): each backend must define the member itself.
            owner = next(klass for klass in backend.__mro__ if name in vars(klass))
            assert owner is not PhysicsBatch, (backend.__name__, name)


def test_a_mujoco_batch_is_a_physics_batch_and_answers_the_capability():
    model = load_model("half_cheetah.xml")
    one, two = MujocoBatch(model, 1), MujocoBatch(model, 2)
    assert isinstance(one, PhysicsBatch) and isinstance(two, PhysicsBatch)
    assert one.supports_aliased_single_step and not two.supports_aliased_single_step


def test_a_backend_without_the_capability_refuses_the_single_step():
    class Minimal(PhysicsBatch):  # the protocol's defaults for the optional capability
        pass

    minimal = Minimal()
    assert minimal.supports_aliased_single_step is False
    with pytest.raises(NotImplementedError, match="supports_aliased_single_step"):
        minimal.advance_one(1)
    with pytest.raises(NotImplementedError, match="supports_aliased_single_step"):
        minimal.contact_counts_one([True])


def test_warp_batch_keeps_the_protocol_defaults_for_the_single_step():
    assert WarpBatch.supports_aliased_single_step is PhysicsBatch.supports_aliased_single_step
    assert WarpBatch.advance_one is PhysicsBatch.advance_one


def test_fast_paths_follow_the_capability_not_the_class(monkeypatch):
    """An env on a physics without the capability steps through SafeEnv's path, with the same values."""
    nav = sg_torchrl.make("SafetyPointGoal1-v0", seed=3)
    assert SingleNavigationStep.of(nav, NavigationEnv) is not None
    monkeypatch.setattr(MujocoBatch, "supports_aliased_single_step", property(lambda self: False))
    assert SingleNavigationStep.of(nav, NavigationEnv) is None
    velocity = sg_torchrl.make("SafetyHalfCheetahVelocity-v1", seed=3)
    assert velocity._single_plan() is None


def test_no_isinstance_of_a_backend_class_outside_the_backend_modules():
    import pathlib
    import re
    root = pathlib.Path(sg_torchrl.__file__).parent
    allowed = {"physics.py", "warp_physics.py", "backends.py", "physics_protocol.py"}
    pattern = re.compile(r"isinstance\([^)]*\b(MujocoBatch|WarpBatch)\b")
    offenders = [str(path) for path in root.rglob("*.py")
                 if path.name not in allowed and pattern.search(path.read_text())]
    assert not offenders, offenders


def test_protocol_members_cover_what_the_envs_read():
    """Every ``physics.<member>`` the env packages read is a member of the protocol."""
    import pathlib
    import re
    root = pathlib.Path(sg_torchrl.__file__).parent
    used = set()
    for path in root.rglob("*.py"):
        if path.name in ("physics.py", "warp_physics.py", "contacts.py"):
            continue
        used |= set(re.findall(r"\bphysics\.([a-z_]+)\b", path.read_text()))
    members = set(PROTOCOL_MEMBERS)
    modules = {"physics_protocol", "warp_physics"}  # "sg_torchrl.envs.physics.<...>" in docstrings: module paths
    assert used - members - modules - {"MujocoBatch", "WarpBatch"} <= set(), sorted(used - members - modules)
    assert inspect.signature(MujocoBatch.step).parameters.keys() == inspect.signature(PhysicsBatch.step).parameters.keys()
    assert np.all([callable(getattr(MujocoBatch, name)) for name in ("advance_one", "contact_counts_one")])
