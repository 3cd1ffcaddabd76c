"""``sg_torchrl.modules``: direct-write TensorDict modules give the parent's outputs without its per-call import scan."""

from __future__ import annotations

import importlib.util

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import ValueOperator

from sg_torchrl.modules import DirectTensorDictModule, DirectValueOperator, make_actor_critics


class TwoHeads(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.linear = nn.Linear(3, 4)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        y = self.linear(x)
        return y[..., :2], y[..., 2:].exp()


def _batch() -> TensorDict:
    return TensorDict({"observation": torch.randn(5, 3)}, batch_size=[5])


@pytest.mark.parametrize("out_keys", [["loc", "scale"], [("group", "loc"), "_"]])
def test_same_outputs_as_tensordict_module(out_keys):
    heads, data = TwoHeads(), _batch()
    reference = TensorDictModule(heads, in_keys=["observation"], out_keys=out_keys)(data.clone())
    direct = DirectTensorDictModule(heads, in_keys=["observation"], out_keys=out_keys)(data.clone())
    assert set(direct.keys(True, True)) == set(reference.keys(True, True))
    for key in reference.keys(True, True):
        torch.testing.assert_close(direct[key], reference[key], rtol=0, atol=0)


def test_value_operator_same_values_and_gradients():
    mlp = nn.Linear(3, 1)
    data = _batch()
    expected = ValueOperator(mlp, in_keys=["observation"])(data.clone())["state_value"]
    value = DirectValueOperator(mlp, in_keys=["observation"])(data.clone())["state_value"]
    torch.testing.assert_close(value, expected, rtol=0, atol=0)
    value.sum().backward()
    assert mlp.weight.grad is not None and torch.isfinite(mlp.weight.grad).all()


def test_separate_output_tensordict_uses_the_general_path():
    module = DirectTensorDictModule(TwoHeads(), in_keys=["observation"], out_keys=["loc", "scale"])
    data = _batch()
    out = module(data, tensordict_out=TensorDict(batch_size=[5]))
    assert set(out.keys()) == {"loc", "scale"} and "loc" not in data.keys()


def test_forward_does_not_scan_for_optional_packages(monkeypatch):
    actor, critic, cost_critic = make_actor_critics(3, _action_spec(), [8, 8])
    data = _batch()
    calls = []
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: calls.append(name) or real_find_spec(name, *a))
    actor(data)
    critic(data)
    cost_critic(data)
    assert calls == []
    assert {"loc", "scale", "action", "state_value", "cost_value"} <= set(data.keys())


def _action_spec():
    from torchrl.data import Bounded

    return Bounded(-1.0, 1.0, shape=(2,))
