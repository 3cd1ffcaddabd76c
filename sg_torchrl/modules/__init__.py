"""sg_torchrl's networks, in one place: single-agent, seed-stacked and multi-agent.

* :mod:`~sg_torchrl.modules.direct`: :class:`DirectTensorDictModule`, :class:`DirectValueOperator`,
  TensorDict modules that write tensor outputs straight into the TensorDict (every network below
  is one of them);
* :mod:`~sg_torchrl.modules.mlp`: SafePO's single-agent Gaussian actor and reward / cost critics
  (:func:`make_actor_critics`, :func:`make_actor`, :func:`make_value`), reading the flat vector
  or, through :class:`ObservationEncoder`, pixels (:class:`ObservationLayout` says which);
* :mod:`~sg_torchrl.modules.cnn`: the pixel encoders' convolutional stack as plain data
  (:class:`CNNArchitecture`, :data:`DEFAULT_CNN`; no torch import);
* :mod:`~sg_torchrl.modules.stacked`: S seeds' copies of those networks run as one
  (:class:`StackedMLP`, :class:`StackedActorCritic`), for seed groups;
* :mod:`~sg_torchrl.modules.multi_agent`: per-agent actors and centralised critics for the safe
  multi-agent algorithms (:func:`make_multi_agent_networks`, :class:`MultiAgentNetworks`);
* :mod:`~sg_torchrl.modules.stacked_multi_agent`: S seeds' teams in ``(S, A, ...)`` tensors and their
  actors as one collection policy (:class:`StackedMultiAgentNetworks`, :class:`StackedMultiAgentPolicy`),
  for multi-agent seed groups;
* :mod:`~sg_torchrl.modules.gaussian`: :func:`gaussian_log_prob`, the diagonal Gaussian policy's
  log-density that the stacked actor and the seed-batched objectives share.

The networks depend on neither the trainers (:mod:`sg_torchrl.train`) nor the losses
(:mod:`sg_torchrl.objectives`). Importing this package loads no torch: the names below are imported
from their module on first access (PEP 562), so ``sg-train`` can read :data:`DEFAULT_CNN` while it
checks a command line.
"""

from __future__ import annotations

from sg_torchrl.lazy import lazy_exports

#: Public name -> the module of this package that defines it, imported on first access (PEP 562).
_HOMES = {
    "DirectTensorDictModule": "direct",
    "DirectValueOperator": "direct",
    "CNNArchitecture": "cnn",
    "DEFAULT_CNN": "cnn",
    "DEPTH_RANGE": "mlp",
    "IMAGE_CHUNK": "mlp",
    "EncodedMLP": "mlp",
    "ObservationEncoder": "mlp",
    "ObservationLayout": "mlp",
    "make_actor": "mlp",
    "make_actor_critics": "mlp",
    "make_network": "mlp",
    "make_value": "mlp",
    "StackedActorCritic": "stacked",
    "StackedMLP": "stacked",
    "quiet_layout_warning": "stacked",
    "AgentGaussianHead": "multi_agent",
    "MultiAgentGaussianPolicy": "multi_agent",
    "MultiAgentNetworks": "multi_agent",
    "MultiAgentStateValue": "multi_agent",
    "PerAgentMLP": "multi_agent",
    "make_multi_agent_networks": "multi_agent",
    "StackedMultiAgentNetworks": "stacked_multi_agent",
    "StackedMultiAgentPolicy": "stacked_multi_agent",
    "gaussian_log_prob": "gaussian",
}

__all__ = sorted(_HOMES)


__getattr__, __dir__ = lazy_exports(__name__, {name: f"{__name__}.{home}" for name, home in _HOMES.items()})
