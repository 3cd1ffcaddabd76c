"""Fixtures shared by the test files."""

from __future__ import annotations

import pytest

from sg_torchrl.envs import rendering
from sg_torchrl.envs.rendering import RenderingUnavailable


@pytest.fixture(scope="module")
def backend() -> str:
    """The headless OpenGL backend; skips the test where none works."""
    try:
        return rendering.gl_backend()
    except RenderingUnavailable as error:
        pytest.skip(f"no OpenGL backend for headless rendering: {error}")
