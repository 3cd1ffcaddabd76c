"""The safe dexterous-hand tasks' former home: an alias of :mod:`sg_torchrl.envs.hands`.

The package moved under ``sg_torchrl.envs`` with the other env families. Importing ``sg_torchrl.dexhands``
(or one of its submodules, ``sg_torchrl.dexhands.env``, ...) gives the same objects as before: the names are
re-exported and each submodule name refers to the module of :mod:`sg_torchrl.envs.hands`, so code and
pickles that name the old paths keep working.
"""

import importlib
import sys

from sg_torchrl.envs import hands as _hands

__all__ = list(_hands.__all__)
globals().update({name: getattr(_hands, name) for name in __all__})

#: Submodules reachable under the old name (``import sg_torchrl.dexhands.env``).
SUBMODULES = ("constraints", "env", "multi_agent", "rotations", "scene", "tasks")
for _name in SUBMODULES:
    sys.modules[f"{__name__}.{_name}"] = module = importlib.import_module(f"sg_torchrl.envs.hands.{_name}")
    globals()[_name] = module
del _name, module
