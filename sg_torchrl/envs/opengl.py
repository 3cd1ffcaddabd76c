"""Which OpenGL backend headless rendering uses, and its GL context class.

With ``MUJOCO_GL`` set (``egl``, ``osmesa``, ``glfw``) that backend is used. Unset, the first of EGL
and OSMesa that can actually create a context here is picked, once per process: each candidate is
tried in a short-lived subprocess (about half a second), because PyOpenGL binds one platform per
process and a failed EGL attempt would otherwise rule out OSMesa. Both work without a GPU through
Mesa's software rasteriser (llvmpipe). When neither works, :class:`RenderingUnavailable` names the
missing system library (Debian/Ubuntu: ``libegl1``, ``libgl1``, ``libosmesa6``; ``make install``
installs them when it can). :mod:`sg_torchrl.envs.rendering` re-exports :func:`gl_backend` and
:class:`RenderingUnavailable`.
"""

from __future__ import annotations

import ctypes.util
import os
import subprocess
import sys

__all__ = ["INSTALL_HINT", "RenderingUnavailable", "context_class", "gl_backend"]

# Backend -> (library PyOpenGL loads, Debian/Ubuntu packages providing it and what it needs).
_LIBRARIES = {
    "egl": ("EGL", "libegl1 (with a driver such as libegl-mesa0) and libgl1"),
    "osmesa": ("OSMesa", "libosmesa6"),
}
INSTALL_HINT = (
    "Install the Mesa libraries (Debian/Ubuntu: `apt-get install libegl1 libgl1 libosmesa6`; "
    "`make install` does this when it runs as root) or set MUJOCO_GL to a backend that works here."
)


class RenderingUnavailable(RuntimeError):
    """No OpenGL backend can render here (the message says what is missing)."""


_backend: str | None = None
_backend_error: str | None = None

# Run in a fresh interpreter to test one backend: create a context and MuJoCo's render context.
_PROBE = """
import sys
import mujoco
backend = sys.argv[1]
module = __import__("mujoco." + backend, fromlist=["GLContext"])
context = module.GLContext(16, 16)
context.make_current()
render_context = mujoco.MjrContext(mujoco.MjModel.from_xml_string("<mujoco/>"), 100)
render_context.free()
context.free()
"""


def _probe(backend: str) -> str | None:
    """Why ``backend`` cannot render here, or ``None`` if it can."""
    library, packages = _LIBRARIES[backend]
    if ctypes.util.find_library(library) is None:
        return f"lib{library}.so not found (Debian/Ubuntu package: {packages})"
    env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
    try:
        result = subprocess.run([sys.executable, "-c", _PROBE, backend], env=env, capture_output=True,
                                text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as error:
        return f"probe failed: {error}"
    if result.returncode == 0:
        return None
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    return f"{lines[-1] if lines else f'exit code {result.returncode}'} (needs {packages})"


def gl_backend() -> str:
    """The OpenGL backend rendering uses in this process: ``"egl"``, ``"osmesa"`` or ``"glfw"``.

    ``MUJOCO_GL`` when set; otherwise the first of EGL and OSMesa that works (see the module
    docstring), decided once per process. Raises :class:`RenderingUnavailable` when none works.
    """
    global _backend, _backend_error
    if _backend is not None:
        return _backend
    if _backend_error is not None:
        raise RenderingUnavailable(_backend_error)
    requested = os.environ.get("MUJOCO_GL", "").strip().lower()
    if requested in ("disable", "disabled", "off", "false", "0"):
        _backend_error = f"rendering is disabled (MUJOCO_GL={requested!r})"
        raise RenderingUnavailable(_backend_error)
    if requested:
        _backend = requested if requested in ("egl", "osmesa") else "glfw"
        return _backend
    # PyOpenGL binds the platform named by PYOPENGL_PLATFORM: only that backend can work then.
    platform = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    candidates = [platform] if platform in _LIBRARIES else list(_LIBRARIES)
    reasons = []
    for candidate in candidates:
        reason = _probe(candidate)
        if reason is None:
            _backend = candidate
            return _backend
        reasons.append(f"{candidate}: {reason}")
    _backend_error = "no headless OpenGL backend works here (" + "; ".join(reasons) + "). " + INSTALL_HINT
    raise RenderingUnavailable(_backend_error)


def context_class(backend: str) -> type:
    """The ``GLContext`` class of ``backend`` (imports the backend's PyOpenGL platform)."""
    # PyOpenGL reads PYOPENGL_PLATFORM once, when it is first imported (MuJoCo's EGL and OSMesa
    # modules set it). Put it back afterwards so that child processes choose their own backend.
    previous = os.environ.get("PYOPENGL_PLATFORM")
    if backend in _LIBRARIES and previous is None:
        os.environ["PYOPENGL_PLATFORM"] = backend
    try:
        if backend == "egl":
            from mujoco.egl import GLContext
        elif backend == "osmesa":
            from mujoco.osmesa import GLContext
        else:
            from mujoco.glfw import GLContext
    except Exception as error:  # ImportError, or PyOpenGL failing to load the library
        raise RenderingUnavailable(f"cannot load the {backend!r} OpenGL backend: {error}. {INSTALL_HINT}") from error
    finally:
        if previous is None:
            os.environ.pop("PYOPENGL_PLATFORM", None)
    return GLContext
