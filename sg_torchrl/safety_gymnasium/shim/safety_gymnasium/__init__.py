"""Stand-in ``safety_gymnasium`` for the child processes of ``python -m sg_torchrl.safety_gymnasium``.

The launcher puts this file's parent directory first on ``sys.path`` and ``PYTHONPATH``. A child
process that does not inherit the parent's import hook (a ``spawn`` or ``forkserver`` worker, which
re-imports the script, or any Python subprocess) finds this package for ``import safety_gymnasium``;
it installs the alias (:func:`sg_torchrl.safety_gymnasium.install_alias`) and hands the import
sg_torchrl's drop-in in its place, so ``safety_gymnasium`` and its submodules resolve as in the
parent. Where the alias is already installed (the launcher's own process, forked workers), the
alias's finder answers first and this file is never run.
"""

import sys

from sg_torchrl.safety_gymnasium.alias import install_alias

# install_alias refuses to run while another module holds the name: this stand-in leaves first.
# The import system then returns what sys.modules holds under the name: the drop-in.
del sys.modules[__name__]
install_alias()
