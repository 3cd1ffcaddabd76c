"""``python -m sg_torchrl.safety_gymnasium script.py [args...]``: run a Safety-Gymnasium script unchanged.

Runs ``script.py`` as ``__main__`` with ``sys.argv`` set to ``[script.py, args...]`` and its directory
first on ``sys.path`` (as ``python script.py`` would); ``-m module [args...]`` runs a module instead
(e.g. ``python -m sg_torchrl.safety_gymnasium -m safepo.single_agent.ppo_lag --task ...``).
Before that, it

* installs the alias (:func:`sg_torchrl.safety_gymnasium.install_alias`) in this process, so that
  the script's and its libraries' ``import safety_gymnasium`` resolve to sg_torchrl's drop-in;
* makes the alias reach every child process: forked workers inherit it; for the others (``spawn``
  and ``forkserver`` workers, which re-import the script, and Python subprocesses) the directory of
  a stand-in ``safety_gymnasium`` package (:data:`SHIM_DIR`, ``shim/safety_gymnasium``) goes first
  on ``sys.path`` (which ``multiprocessing`` hands its spawned workers) and on ``PYTHONPATH`` (which
  every subprocess inherits); importing the stand-in installs the alias in that process;
* restores the platform's default multiprocessing start method (``fork`` on Linux, ``spawn`` on
  macOS and Windows), which Safety-Gymnasium's users' code was written for: importing TorchRL sets
  the global default to ``spawn``, under which workers re-import the whole script (slower to start)
  and, where a library's workers wait on a pipe for a ``close`` that never comes (SafePO's
  multi-agent vector env), print ``EOFError`` tracebacks at exit. ``--start-method METHOD`` before
  the script chooses another one (``spawn``, ``forkserver``, ``fork``).
"""

from __future__ import annotations

import multiprocessing
import os
import runpy
import sys

from sg_torchrl.safety_gymnasium.alias import install_alias

__all__ = ["SHIM_DIR", "export_alias", "main", "platform_start_method"]

SHIM_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "shim")
"""The directory holding the stand-in ``safety_gymnasium`` package for child processes."""

_USAGE = "usage: python -m sg_torchrl.safety_gymnasium [--start-method METHOD] (script.py | -m module) [args...]"


def platform_start_method() -> str:
    """Python's own default start method here (before any library changes it)."""
    if sys.platform in ("darwin", "win32"):
        return "spawn"
    return "forkserver" if sys.version_info >= (3, 14) else "fork"


def export_alias() -> None:
    """Install the alias here and make child processes install it (module docstring)."""
    install_alias()
    if SHIM_DIR not in sys.path:
        sys.path.insert(0, SHIM_DIR)
    inherited = [path for path in os.environ.get("PYTHONPATH", "").split(os.pathsep) if path and path != SHIM_DIR]
    os.environ["PYTHONPATH"] = os.pathsep.join([SHIM_DIR, *inherited])


def main(argv: list[str]) -> None:
    """Run the script or module ``argv`` names, with the alias installed here and in child processes."""
    argv = list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip() + "\n\n" + _USAGE)
        raise SystemExit(0 if argv else 2)
    start_method = platform_start_method()
    if argv[0] == "--start-method":
        if len(argv) < 3:
            raise SystemExit(_USAGE)
        start_method, argv = argv[1], argv[2:]
        if start_method not in multiprocessing.get_all_start_methods():
            raise SystemExit(f"--start-method {start_method!r}: this platform has "
                             f"{multiprocessing.get_all_start_methods()}")
    export_alias()
    multiprocessing.set_start_method(start_method, force=True)
    if argv[0] == "-m":
        if len(argv) < 2:
            raise SystemExit(_USAGE)
        sys.argv = argv[1:]
        runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
    else:
        sys.argv = argv
        # As `python script.py`: the script's directory on sys.path, before anything but the stand-in.
        script_dir = os.path.dirname(os.path.abspath(argv[0]))
        if script_dir not in sys.path:
            sys.path.insert(1, script_dir)
        runpy.run_path(argv[0], run_name="__main__")


if __name__ == "__main__":
    main(sys.argv[1:])
