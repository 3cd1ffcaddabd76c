"""``python -m sg_torchrl.safety_gymnasium script.py [args...]``: run a Safety-Gymnasium script unchanged.

Installs the alias (:func:`sg_torchrl.safety_gymnasium.install_alias`), so that the script's and its
libraries' ``import safety_gymnasium`` resolve to sg_torchrl's drop-in, then runs ``script.py`` as
``__main__`` with ``sys.argv`` set to ``[script.py, args...]``. ``-m module [args...]`` runs a module
instead (e.g. ``python -m sg_torchrl.safety_gymnasium -m safepo.single_agent.ppo_lag --task ...``).
"""

from __future__ import annotations

import runpy
import sys

from sg_torchrl.safety_gymnasium.alias import install_alias

_USAGE = "usage: python -m sg_torchrl.safety_gymnasium (script.py | -m module) [args...]"


def main(argv: list[str]) -> None:
    """Run the script or module ``argv`` names, with the alias installed."""
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip() + "\n\n" + _USAGE)
        raise SystemExit(0 if argv else 2)
    install_alias()
    if argv[0] == "-m":
        if len(argv) < 2:
            raise SystemExit(_USAGE)
        sys.argv = argv[1:]
        runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
    else:
        sys.argv = list(argv)
        runpy.run_path(argv[0], run_name="__main__")


if __name__ == "__main__":
    main(sys.argv[1:])
