"""``--compile``'s one mechanism: a function run through ``torch.compile``, or eagerly where compiling fails.

Every compiled piece of the single-agent on-policy engine (the minibatch losses,
:class:`~sg_torchrl.train.fused.FusedFirstOrderStep`; the masked Adam update,
:class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam`) is a :class:`CompileFallback`: the compiled form is
``torch.compile(..., dynamic=False)`` (a graph per input shape, a handful per run), and when compiling or
running it raises (no C++ compiler, an op inductor cannot lower) the owner warns once, records
:attr:`CompileFallback.compile_error` and runs the eager function from then on.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import torch

__all__ = ["CompileFallback"]


class CompileFallback:
    """``eager`` through ``torch.compile`` when ``compile``, falling back to ``eager`` itself on an error.

    Args:
        eager: the function (its arguments: tensors, containers of tensors, constants).
        owner: who runs it, for the warning (``"FusedFirstOrderStep"``).
        compile: compile it; ``False``: :meth:`__call__` is ``eager``'s call, nothing else.
        compiled_form: what to compile instead of ``eager`` (the same math written for inductor,
            e.g. with a keyword set); defaults to ``eager``.
    """

    def __init__(self, eager: Callable[..., Any], *, owner: str, compile: bool,
                 compiled_form: Callable[..., Any] | None = None) -> None:
        self.eager = eager
        self.owner = owner
        self.function = torch.compile(compiled_form or eager, dynamic=False) if compile else eager
        #: The first line of the error that made a compiled function fall back to eager (``None``: none did).
        self.compile_error: str | None = None

    @property
    def compiled(self) -> bool:
        """Whether calls go through the compiled form (``False`` when not asked for or after a fallback)."""
        return self.function is not self.eager

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        try:
            return self.function(*args, **kwargs)
        except Exception as error:  # noqa: BLE001 -- compiling failed: say so once, go on eagerly
            if not self.compiled:
                raise
            self.fall_back(error)
            return self.eager(*args, **kwargs)

    def fall_back(self, error: Exception) -> None:
        """Record ``error``, warn, and run eagerly from now on."""
        self.compile_error = f"{type(error).__name__}: {error}".splitlines()[0]
        warnings.warn(f"{self.owner}: torch.compile failed, running eagerly ({self.compile_error})", stacklevel=4)
        self.function = self.eager
