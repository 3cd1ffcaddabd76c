"""The losses and transforms use TorchRL's private names only where TorchRL documents them as the way in.

The scan reads the source (AST) of ``sg_torchrl/objectives`` and ``sg_torchrl/envs/transforms.py`` for
every TorchRL private name they touch: an attribute (``self._x``, ``super()._x``), a method or class
attribute they override, and an import of a private name from a ``torchrl`` module. TorchRL's private
names are taken from the installed classes our losses and transforms subclass (and a built
``ClipPPOLoss``'s instance attributes, less ``torch.nn.Module``'s own), so a name TorchRL adds is caught too. Each allowed name says
why it stays; anything else fails with its file and line.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torchrl.envs.transforms import RewardSum, Transform
from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss, DDPGLoss, LossModule, PPOLoss, SACLoss, TD3Loss
from torchrl.objectives.multiagent import MAPPOLoss
from torchrl.objectives.value import GAE, ValueEstimatorBase

ROOT = Path(__file__).resolve().parents[1]
SCANNED = [*sorted((ROOT / "sg_torchrl" / "objectives").rglob("*.py")), ROOT / "sg_torchrl" / "envs" / "transforms.py"]

#: The private TorchRL names the scanned modules may use, and why each stays.
ALLOWED = {
    "_AcceptedKeys": "LossModule's documented way to declare the keys set_keys() configures",
    "_forward_value_estimator_keys": "LossModule's documented hook forwarding set_keys() to the value estimator "
                                     "(the cost estimator follows the keys through it)",
    "_set_in_keys": "the in-keys hook of PPOLoss, called by LossModule's default _forward_value_estimator_keys "
                    "after set_keys()",
    "_in_keys": "the list _set_in_keys fills, which PPOLoss's in_keys property returns (the multi-agent loss "
                "extends it)",
    "_schedulable_buffers": "LossModule's documented class attribute for schedulable coefficients",
    "_reduce_loss": "LossModule's one implementation of the documented reduction / loss_mask_key options; "
                    "no public form exists and a copy would drift",
    "_reset": "Transform's reset hook (RewardSum resets its sums there); no public form exists",
    "_generate_episode_reward_spec": "RewardSum's one builder of the sums' spec, which its public "
                                     "transform_*_spec methods read; overriding those would copy them",
}


def _torchrl_private_names() -> frozenset[str]:
    """Single-underscore names of the TorchRL classes sg_torchrl subclasses, and of a built ClipPPOLoss."""
    # The off-policy losses subclass SACLoss, TD3Loss and DDPGLoss: their private names are scanned for too.
    classes = (LossModule, PPOLoss, ClipPPOLoss, MAPPOLoss, SACLoss, TD3Loss, DDPGLoss, ValueEstimatorBase, GAE,
               Transform, RewardSum)
    names = {name for cls in classes for name in dir(cls)}
    actor = ProbabilisticActor(
        TensorDictModule(torch.nn.Sequential(MLP(in_features=3, out_features=2, num_cells=[4]),
                                             AddStateIndependentNormalScale(2)),
                         in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"], distribution_class=IndependentNormal, return_log_prob=True)
    loss = ClipPPOLoss(actor, ValueOperator(MLP(in_features=3, out_features=1, num_cells=[4]), in_keys=["observation"]))
    names |= set(vars(loss))
    names -= set(dir(torch.nn.Module))  # torch's own (``_apply``, ``_buffers``, ...), not TorchRL's
    return frozenset(name for name in names if name.startswith("_") and not name.startswith("__"))


def private_uses(source: str, private: frozenset[str]) -> list[tuple[int, str]]:
    """``(line, name)`` for each use of a name in ``private`` (attributes, overrides) and each private torchrl import."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and node.attr in private:
            found.append((node.lineno, node.attr))
        elif isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and item.name in private:
                    found.append((item.lineno, item.name))
                targets = item.targets if isinstance(item, ast.Assign) else (
                    [item.target] if isinstance(item, ast.AnnAssign) else [])
                found.extend((item.lineno, t.id) for t in targets if isinstance(t, ast.Name) and t.id in private)
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "torchrl":
            found.extend((node.lineno, alias.name) for alias in node.names if alias.name.startswith("_"))
    return found


@pytest.fixture(scope="module")
def uses() -> dict[str, list[str]]:
    private = _torchrl_private_names()
    by_name: dict[str, list[str]] = {}
    for path in SCANNED:
        for line, name in private_uses(path.read_text(), private):
            by_name.setdefault(name, [])
            if f"{path.relative_to(ROOT)}:{line}" not in by_name[name]:
                by_name[name].append(f"{path.relative_to(ROOT)}:{line}")
    return by_name


def test_only_allowed_private_torchrl_names_are_used(uses):
    unexpected = {name: where for name, where in uses.items() if name not in ALLOWED}
    assert not unexpected, (
        f"private TorchRL names used outside the allowed list (use public API or our own code, or add the name "
        f"to ALLOWED with the reason it must stay): {unexpected}"
    )


def test_every_allowed_name_is_still_needed(uses):
    assert set(ALLOWED) <= set(uses), f"no longer used, drop from ALLOWED: {sorted(set(ALLOWED) - set(uses))}"


def test_the_scan_finds_calls_overrides_and_imports():
    private = _torchrl_private_names()
    assert {"_log_weight", "_get_entropy", "_clear_weakrefs", "_has_critic", "_asymmetric_clip"} <= private
    source = (
        "from torchrl.envs.transforms.utils import _get_reset\n"
        "class L(ClipPPOLoss):\n"
        "    def _maybe_normalize_advantage(self, a, td, *, update_norm):\n"
        "        return a\n"
        "    def forward(self, td):\n"
        "        return self._log_weight(td, adv_shape=()) if self._has_critic else super()._get_entropy(td)\n"
    )
    assert sorted(private_uses(source, private)) == [
        (1, "_get_reset"), (3, "_maybe_normalize_advantage"), (6, "_get_entropy"), (6, "_has_critic"),
        (6, "_log_weight"),
    ]
