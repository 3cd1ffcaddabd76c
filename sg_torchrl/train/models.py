"""SafePO's actor and critics as TorchRL modules.

SafePO's ``ActorVCritic`` (the networks behind the paper's single-agent results): a Gaussian
actor whose mean is a tanh MLP and whose log-std is a state-independent parameter initialised to
0, plus separate reward and cost value MLPs of the same shape (no sharing). PyTorch's default
``Linear`` initialisation, as SafePO.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.nn import AddStateIndependentNormalScale
from torch import nn
from torchrl.data import TensorSpec
from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor

from sg_torchrl.modules import DirectTensorDictModule, DirectValueOperator

__all__ = ["make_actor", "make_value", "make_actor_critics"]


def make_actor(observation_dim: int, action_spec: TensorSpec, hidden_sizes: Sequence[int]) -> ProbabilisticActor:
    """Gaussian policy writing ``loc``, ``scale``, ``action`` and ``action_log_prob``."""
    action_dim = int(action_spec.shape[-1])
    body = nn.Sequential(
        MLP(in_features=observation_dim, out_features=action_dim, num_cells=list(hidden_sizes),
            activation_class=nn.Tanh),
        AddStateIndependentNormalScale(action_dim, scale_mapping="exp", init_value=0.0),
    )
    return ProbabilisticActor(
        DirectTensorDictModule(body, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=action_spec,
        distribution_class=IndependentNormal,
        return_log_prob=True,
        default_interaction_type="random",
    )


def make_value(observation_dim: int, hidden_sizes: Sequence[int], out_key: str) -> DirectValueOperator:
    """A tanh-MLP state-value network writing ``out_key``."""
    mlp = MLP(in_features=observation_dim, out_features=1, num_cells=list(hidden_sizes), activation_class=nn.Tanh)
    return DirectValueOperator(mlp, in_keys=["observation"], out_keys=[out_key])


def make_actor_critics(
    observation_dim: int, action_spec: TensorSpec, hidden_sizes: Sequence[int]
) -> tuple[ProbabilisticActor, DirectValueOperator, DirectValueOperator]:
    """Actor, reward critic (``state_value``) and cost critic (``cost_value``)."""
    return (
        make_actor(observation_dim, action_spec, hidden_sizes),
        make_value(observation_dim, hidden_sizes, "state_value"),
        make_value(observation_dim, hidden_sizes, "cost_value"),
    )


def count_parameters(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
