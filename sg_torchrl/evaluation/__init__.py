"""Evaluate, watch and export a trained agent: ``sg-eval`` and :func:`load_policy`.

* :func:`load_policy` (also ``sg_torchrl.load_policy``): a run's trained policy (any family: on-policy,
  off-policy, a multi-agent team), observation normaliser folded in, as a TorchRL ``TensorDictModule``
  with ``act(obs)`` for numpy (:mod:`~sg_torchrl.evaluation.policy`; one loader per kind of run,
  :mod:`~sg_torchrl.evaluation.loaders`; the networks, :mod:`~sg_torchrl.evaluation.networks`);
* :func:`export_policy`: that policy's mean action as a ``torch.export`` file that runs with torch
  alone (:mod:`~sg_torchrl.evaluation.export`);
* :func:`record_evaluation`: the frames of evaluation episodes with their running cost drawn on
  them (:mod:`~sg_torchrl.evaluation.video`);
* ``sg-eval RUN_DIR`` (:mod:`~sg_torchrl.evaluation.cli`): N episodes per seed, a table, per-episode
  CSV and a summary JSON; its defaults reproduce the evaluation ``sg-train`` ran at the end of
  training, figure for figure.

Importing this package loads no torch (``sg-eval`` checks its command line first); the names below
are imported from their module on first access (PEP 562).
"""

from __future__ import annotations

from sg_torchrl.lazy import lazy_exports

#: Public name -> the module of this package that defines it.
_HOMES = {
    "PolicyLoadError": "policy",
    "ObservationScaler": "networks",
    "OffPolicyActorNetwork": "networks",
    "PolicyNetwork": "networks",
    "TrainedPolicy": "networks",
    "load_policy": "policy",
    "read_run": "policy",
    "export_policy": "export",
    "record_evaluation": "video",
}

__all__ = sorted(_HOMES)


__getattr__, __dir__ = lazy_exports(__name__, {name: f"{__name__}.{home}" for name, home in _HOMES.items()})
