"""TensorDict modules that write their tensor outputs straight into the TensorDict.

tensordict 0.14's :class:`~tensordict.nn.TensorDictModule` passes every output through
:meth:`TensorDict.from_any`, which returns a plain tensor unchanged, but only after asking
``importlib.util.find_spec("pandas")``: with pandas not installed that is a scan of ``sys.path``
on every call. Our networks are called once per env step during collection and several times per
minibatch in the update (actor, reward critic, cost critic), where this scan measured 12-20 % of a
PPO-Lag minibatch step on the 2-core machine kind. These subclasses store tensor outputs directly
and hand anything else (a TensorDict, a tuple) to the parent's conversion, so their outputs are
identical to the parent's.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.modules import ValueOperator

__all__ = ["DirectTensorDictModule", "DirectValueOperator"]


class _DirectWrite:
    """Mixin for :class:`~tensordict.nn.TensorDictModule` subclasses: store plain tensors as they are."""

    def _write_to_tensordict(
        self,
        tensordict: TensorDictBase,
        tensors: Sequence[Tensor],
        tensordict_out: TensorDictBase | None = None,
        out_keys: Iterable[NestedKey] | None = None,
    ) -> TensorDictBase:
        keys = list(self.out_keys_source if out_keys is None else out_keys)
        if (
            self.inplace is not True
            or tensordict_out is not None
            or len(keys) != len(tensors)
            or not all(type(tensor) is Tensor for tensor in tensors)
        ):  # anything unusual: the parent's general path
            return super()._write_to_tensordict(tensordict, tensors, tensordict_out, keys)
        for key, tensor in zip(keys, tensors):
            if key != "_":
                tensordict.set(key, tensor)
        return tensordict


class DirectTensorDictModule(_DirectWrite, TensorDictModule):
    """:class:`~tensordict.nn.TensorDictModule` with direct tensor writes (same arguments, same outputs)."""


class DirectValueOperator(_DirectWrite, ValueOperator):
    """:class:`~torchrl.modules.ValueOperator` with direct tensor writes (same arguments, same outputs)."""
