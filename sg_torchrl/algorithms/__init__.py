"""The algorithms ``sg-train`` runs, as data: :mod:`sg_torchrl.algorithms.manifest`.

Free of torch, like the manifest (the builders that need torch are :mod:`sg_torchrl.train.algorithms`
and :mod:`sg_torchrl.train.multi_agent`).
"""

from sg_torchrl.algorithms.manifest import (
    AlgorithmEntry,
    BASELINES,
    ENTRIES,
    SECOND_ORDER,
    UnknownAlgorithmError,
    baseline,
    get,
    names,
    rows,
)

__all__ = [
    "AlgorithmEntry", "BASELINES", "ENTRIES", "SECOND_ORDER", "UnknownAlgorithmError", "baseline", "get", "names",
    "rows",
]
