"""Choosing the physics backend (:mod:`sg_torchrl.envs.backends`): validation that needs no MuJoCo Warp.

These run everywhere (CI has no MuJoCo Warp); the backend itself is tested in
``test_warp_backend.py``, which skips without it.
"""

from __future__ import annotations

import sys

import pytest

from sg_torchrl.envs import make
from sg_torchrl.envs.backends import SimulatorOptions, make_physics
from sg_torchrl.envs.physics import MujocoBatch
from sg_torchrl.envs.registry import env_options
from sg_torchrl.envs.velocity.robots import load_model

#: the envs built on ShadowHandEnv or VelocityEnv, single- and multi-agent
IDS = ["SafetyHalfCheetahVelocity-v1", "Safety2x3HalfCheetahVelocity-v0", "ShadowHandOverSafeJoint-v0",
       "MultiAgentShadowHandCatchOver2UnderarmSafeFinger-v0"]


@pytest.mark.parametrize("env_id", IDS)
def test_backend_options_are_offered_through_the_registry(env_id):
    assert {"backend", "warp_device", "warp_options"} <= set(env_options(env_id))


def test_cpu_is_the_default_backend():
    env = make("SafetyHalfCheetahVelocity-v1", num_envs=2)
    assert type(env.physics) is MujocoBatch
    explicit = make("SafetyHalfCheetahVelocity-v1", num_envs=2, backend="cpu")
    assert type(explicit.physics) is MujocoBatch


@pytest.mark.parametrize("env_id", ["SafetyHalfCheetahVelocity-v1", "ShadowHandOverSafeJoint-v0"])
def test_unknown_backend_names_the_choices(env_id):
    with pytest.raises(ValueError, match=rf"{env_id}: option backend must be one of 'cpu', 'warp', got 'gpu'"):
        make(env_id, num_envs=1, backend="gpu")


def test_warp_with_threads_is_refused():
    with pytest.raises(ValueError, match="physics_threads=2 applies to backend='cpu' only"):
        make("SafetyHalfCheetahVelocity-v1", num_envs=2, backend="warp", physics_threads=2)


def test_warp_settings_need_the_warp_backend():
    with pytest.raises(ValueError, match="warp_device='cpu' applies to backend='warp' only"):
        make("SafetyHalfCheetahVelocity-v1", num_envs=2, warp_device="cpu")
    with pytest.raises(ValueError, match="warp_options=.* applies to backend='warp' only"):
        make("ShadowHandOverSafeJoint-v0", num_envs=1, warp_options={"njmax": 512})


def test_warp_without_mujoco_warp_says_how_to_install_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco_warp", None)  # `import mujoco_warp` now raises ImportError
    with pytest.raises(ImportError, match=r"pip install 'sg_torchrl\[warp\]'"):
        make("SafetyHalfCheetahVelocity-v1", num_envs=2, backend="warp")
    with pytest.raises(ImportError, match=r"sg_torchrl\[warp\]"):
        make_physics(load_model("half_cheetah.xml"), 2, SimulatorOptions(backend="warp"))
