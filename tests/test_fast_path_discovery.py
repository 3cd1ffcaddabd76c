"""The one-simulator fast paths find the hooks a subclass redefines by themselves (sg_torchrl.envs.step_hooks)."""

from __future__ import annotations

import numpy as np
import pytest

import sg_torchrl
from sg_torchrl.envs.base import SafeEnv
from sg_torchrl.envs.multi_agent.env import MultiAgentVelocityEnv
from sg_torchrl.envs.navigation.env import NavigationEnv
from sg_torchrl.envs.navigation.single import SingleNavigationStep
from sg_torchrl.envs.step_hooks import StepHooks, step_hook
from sg_torchrl.envs.registry import EnvEntry, register, unregister
from sg_torchrl.envs.velocity.env import VelocityEnv
from sg_torchrl.gym import SafetyGymnasiumEnv


class ObserveTwice(NavigationEnv):
    def _observe(self):  # a hook the fast path does the work of
        return super()._observe()


class Renamed(NavigationEnv):
    def describe(self) -> str:  # not a step hook
        return "renamed"


class ObservedGrandchild(ObserveTwice):
    pass


class PositionElsewhere(VelocityEnv):
    def _position(self):  # marked in VelocityEnv itself
        return super()._position()


class OwnStep(VelocityEnv):
    def _step(self, tensordict):
        return super()._step(tensordict)


def test_navigation_subclass_redefining_a_hook_gets_no_fast_path():
    assert SingleNavigationStep.of(NavigationEnv("Point", "Goal", 1), NavigationEnv) is not None
    assert ObserveTwice.hooks_overridden_since(NavigationEnv) == {"_observe"}
    assert SingleNavigationStep.of(ObserveTwice("Point", "Goal", 1), NavigationEnv) is None
    assert SingleNavigationStep.of(ObservedGrandchild("Point", "Goal", 1), NavigationEnv) is None  # inherited redefinition


def test_a_method_that_is_not_a_hook_keeps_the_fast_path():
    assert Renamed.hooks_overridden_since(NavigationEnv) == frozenset()
    assert SingleNavigationStep.of(Renamed("Point", "Goal", 1), NavigationEnv) is not None


def test_velocity_subclass_redefining_its_own_hook_gets_no_fast_path():
    assert VelocityEnv("HalfCheetah")._single_plan() is not None
    assert PositionElsewhere.hooks_overridden_since(VelocityEnv) == {"_position"}
    assert PositionElsewhere("HalfCheetah")._single_plan() is None


def test_the_slow_path_of_a_redefined_hook_gives_the_same_values():
    fast, slow = NavigationEnv("Point", "Goal", 1, seed=5), ObserveTwice("Point", "Goal", 1, seed=5)
    fast.reset(), slow.reset()
    actions = np.random.default_rng(0).uniform(-1, 1, (40, fast.action_dim))
    for action in actions:
        a, b = fast.step_one(action), slow.step_one(action)
        assert a[0].tobytes() == b[0].tobytes() and a[1:] == b[1:]


def test_numpy_step_interface_follows_the_step_in_use():
    assert VelocityEnv("HalfCheetah").numpy_step_interface == "flat"
    assert OwnStep("HalfCheetah").numpy_step_interface is None
    assert OwnStep.hooks_overridden_since(SafeEnv) >= {"_step"}
    multi = MultiAgentVelocityEnv("HalfCheetah", "2x3")
    assert multi.numpy_step_interface == "agent_group"
    assert multi._single_plan() is None  # its _step differs from VelocityEnv's


def test_the_gymnasium_facade_steps_a_redefined_step_through_torchrl():
    env_id = "TestOwnStepHalfCheetah-v0"
    register(EnvEntry(env_id=env_id, constructor=OwnStep, family="velocity", robot="HalfCheetah",
                      task="Velocity", max_episode_steps=1000, kwargs={"robot": "HalfCheetah"}))
    try:  # the id leaves with the test: other tests count the registry's ids
        assert SafetyGymnasiumEnv("SafetyHalfCheetahVelocity-v1")._fast
        assert not SafetyGymnasiumEnv(env_id)._fast
    finally:
        unregister(env_id)


def test_hooks_marked_in_a_new_class_are_discovered():
    class Base(StepHooks):
        @step_hook
        def _measure(self):
            return 1

        def _helper(self):
            return 2

    class Child(Base):
        def _measure(self):
            return 3

        def _helper(self):
            return 4

    assert Child.hooks_overridden_since(Base) == {"_measure"}
    assert Child.hooks_overridden_since(Child) == frozenset()
    with pytest.raises(TypeError, match="not a base"):
        Base.hooks_overridden_since(Child)


def test_registered_envs_keep_their_fast_paths():
    assert SingleNavigationStep.of(sg_torchrl.make("SafetyCarButton1-v0"), NavigationEnv) is not None
    assert sg_torchrl.make("SafetyHopperVelocity-v1")._single_plan() is not None
