"""SimulatorOptions: the one object for the simulator keywords, built from them by every constructor."""

from __future__ import annotations

import dataclasses
import typing

import pytest

import sg_torchrl
from sg_torchrl.envs.options import CONSTRUCTOR_OPTIONS, SIMULATOR_OPTIONS, SimulatorOptions

SIMULATOR_FIELDS = [field.name for field in dataclasses.fields(SimulatorOptions)]


def test_it_is_frozen_with_the_keyword_defaults():
    options = SimulatorOptions()
    assert (options.physics_threads, options.backend, options.warp_device, options.warp_options) == (1, "cpu", None, None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.backend = "warp"


@pytest.mark.parametrize("kwargs, message", [
    ({"backend": "gpu"}, "unknown physics backend 'gpu'"),
    ({"physics_threads": 0}, "physics_threads must be a positive integer"),
    ({"physics_threads": True}, "physics_threads must be a positive integer"),
    ({"warp_device": "cpu"}, "warp_device='cpu' applies to backend='warp' only"),
    ({"warp_options": {"njmax": 9}}, "warp_options=.* applies to backend='warp' only"),
    ({"backend": "warp", "physics_threads": 2}, "physics_threads=2 applies to backend='cpu' only"),
])
def test_bad_combinations_are_refused_naming_the_field(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SimulatorOptions(**kwargs)


def test_the_option_table_rows_are_its_fields():
    hints = typing.get_type_hints(SimulatorOptions)
    assert list(SIMULATOR_OPTIONS) == SIMULATOR_FIELDS
    assert all(SIMULATOR_OPTIONS[name].annotation == hints[name] for name in SIMULATOR_FIELDS)
    for path in ("sg_torchrl.envs.velocity.env:VelocityEnv", "sg_torchrl.envs.multi_agent.env:MultiAgentVelocityEnv",
                 "sg_torchrl.envs.hands.env:ShadowHandEnv", "sg_torchrl.envs.hands.multi_agent:MultiAgentShadowHandEnv"):
        table = CONSTRUCTOR_OPTIONS[path]
        assert {name: table[name] for name in SIMULATOR_FIELDS} == SIMULATOR_OPTIONS, path


@pytest.mark.parametrize("env_id", ["SafetyHalfCheetahVelocity-v1", "Safety2x3HalfCheetahVelocity-v0",
                                    "ShadowHandOverSafeJoint-v0", "MultiAgentShadowHandOverSafeJoint-v0"])
def test_constructors_build_it_from_the_keywords(env_id):
    env = sg_torchrl.make(env_id, physics_threads=2, num_envs=2)
    assert env.simulator_options == SimulatorOptions(physics_threads=2)
    assert env.physics.threads == 2
    env.close()
