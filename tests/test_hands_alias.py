"""``sg_torchrl.dexhands`` still imports: an alias of ``sg_torchrl.envs.hands`` (same modules, same objects)."""

from __future__ import annotations

import pickle
import subprocess
import sys
from pathlib import Path

import sg_torchrl
import sg_torchrl.dexhands as old
import sg_torchrl.envs.hands as new
from sg_torchrl.envs.registry import registry_entry

ROOT = Path(__file__).resolve().parents[1]


def test_the_old_package_re_exports_every_name():
    assert old.__all__ == new.__all__
    for name in new.__all__:
        assert getattr(old, name) is getattr(new, name), name


def test_old_submodule_paths_are_the_new_modules():
    from sg_torchrl.dexhands.env import ShadowHandEnv
    from sg_torchrl.dexhands.multi_agent import MultiAgentShadowHandEnv
    from sg_torchrl.envs.hands import env, multi_agent

    assert ShadowHandEnv is env.ShadowHandEnv and MultiAgentShadowHandEnv is multi_agent.MultiAgentShadowHandEnv
    for name in old.SUBMODULES:
        assert sys.modules[f"sg_torchrl.dexhands.{name}"] is sys.modules[f"sg_torchrl.envs.hands.{name}"]


def test_the_old_paths_import_in_a_fresh_interpreter():
    code = ("import sg_torchrl.dexhands.scene as s, sg_torchrl.envs.hands.scene as t; assert s is t\n"
            "from sg_torchrl.dexhands.tasks import TASKS; assert 'HandOver' in TASKS\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 0, result.stderr


def test_the_registry_names_the_new_path_and_a_pickle_naming_the_old_one_loads():
    assert registry_entry("ShadowHandOverSafeJoint-v0").constructor_path == "sg_torchrl.envs.hands.env:ShadowHandEnv"
    # A pickle written before the move names the class by its old module.
    old_pickle = pickle.dumps(new.ShadowHandEnv, protocol=0).replace(  # text opcodes: names end at a newline
        b"sg_torchrl.envs.hands.env", b"sg_torchrl.dexhands.env")
    assert b"sg_torchrl.dexhands.env" in old_pickle
    assert pickle.loads(old_pickle) is new.ShadowHandEnv
    env = sg_torchrl.make("ShadowHandOverSafeJoint-v0", seed=0)
    assert type(env) is new.ShadowHandEnv
