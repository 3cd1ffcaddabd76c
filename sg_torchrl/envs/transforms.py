"""Cost-aware TorchRL transforms.

sg_torchrl declares ``cost`` (and the per-constraint ``cost_info`` entries) in the env's
*observation* spec, so that ``env.reward_key`` stays unique: a second reward key makes
``env.reward_key`` raise and breaks every transform that reads it (``FrameSkipTransform``,
``UnsqueezeTransform``, ...). The price is that TorchRL transforms which look their inputs up in the
reward spec only reject ``cost``; :class:`EpisodeSum` is the episode accumulator that accepts both.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase, unravel_key
from tensordict.utils import NestedKey, expand_as_right
from torchrl.data import Composite
from torchrl.envs.transforms import RewardSum

__all__ = ["EpisodeSum", "RewardSpec"]


#: What a reward-spec lookup of a cost entry is told: where the cost is declared and which transform sums it.
_COST_HINT = ("sg_torchrl declares 'cost' and 'cost_info' in the observation spec, so that env.reward_key stays "
              "unique; sum them per episode with sg_torchrl.envs.EpisodeSum(in_keys=['reward', 'cost']), which "
              "TorchRL's RewardSum (reward-spec keys only) cannot do")


def _reset_flags(reset_key: NestedKey, tensordict: TensorDictBase) -> torch.Tensor:
    """Which entries of ``reset_key``'s group a reset concerns: the ``_reset`` entry, or all when it is absent.

    TorchRL's reading of a reset signal (as in ``RewardSum``): a partial reset names its entries in
    ``reset_key`` (over the group's batch shape, extra trailing dims any-reduced); no entry means
    every entry resets.
    """
    reset = tensordict.get(reset_key, None)
    group = tensordict.get(reset_key[:-1], None) if isinstance(reset_key, tuple) else tensordict
    if group is None:
        group = tensordict
    if reset is None:
        return torch.ones((), dtype=torch.bool, device=group.device).expand(group.batch_size)
    if reset.ndim > group.ndim:
        reset = reset.flatten(group.ndim, -1).any(-1)
    return reset


class RewardSpec(Composite):
    """The env's full reward spec: a ``Composite`` that says where the cost is when asked for it.

    TorchRL's ``RewardSum(in_keys=["cost"])`` looks ``cost`` up in the reward spec: at reset
    (``full_reward_spec["cost"]``, a bare ``KeyError: 'cost'``) or when it builds its output spec
    (``ValueError: ... not present in the reward spec <repr>``). Both now carry the answer: the
    lookup's ``KeyError`` and this spec's ``repr`` name :class:`EpisodeSum`. Everything else is
    ``Composite``'s own (clones keep the class).
    """

    def __getitem__(self, key):
        try:
            return super().__getitem__(key)
        except KeyError:
            first = key[0] if isinstance(key, tuple) and key else key
            if first in ("cost", "cost_info"):
                raise KeyError(f"{key!r} is not in the reward spec: {_COST_HINT}") from None
            raise

    def __repr__(self) -> str:
        return f"{super().__repr__()}\n# {_COST_HINT}"


class EpisodeSum(RewardSum):
    """Per-episode running sums of reward *and* cost entries.

    TorchRL's :class:`~torchrl.envs.transforms.RewardSum` accumulates its ``in_keys`` over an
    episode and resets the sums on ``reset``, but it only accepts keys of the env's reward spec.
    sg_torchrl envs declare ``cost`` and ``("cost_info", <constraint>)`` in the observation spec
    (see the module docstring), so ``RewardSum(in_keys=["cost"])`` raises ``ValueError``.
    ``EpisodeSum`` is ``RewardSum`` with one change: an input key may live in the full reward spec
    or in the full observation spec. Behaviour, arguments and the written entries are otherwise
    RewardSum's; the sums are registered in the observation spec (or the reward spec with
    ``reward_spec=True``) with the input entry's shape and dtype.

    Example::

        env = TransformedEnv(
            base_env,
            EpisodeSum(
                in_keys=["reward", "cost", ("cost_info", "hazards")],
                out_keys=["episode_reward", "episode_cost", ("episode_cost_info", "hazards")],
            ),
        )

    Give ``out_keys`` explicitly for nested inputs: RewardSum's default output key only replaces
    the last element (``("cost_info", "hazards")`` -> ``("cost_info", "episode_hazards")``), which
    would place the sum inside ``cost_info`` beside the per-step constraint costs.
    """

    def _source_spec(self, in_key: NestedKey) -> Composite:
        """The parent's full spec (reward first, then observation) that declares ``in_key``."""
        parent = self.parent
        if parent is None:
            raise RuntimeError(f"{type(self).__name__} needs a parent env to resolve specs.")
        in_key = unravel_key(in_key)
        candidates = (parent.full_reward_spec, parent.full_observation_spec)
        for spec in candidates:
            if spec is not None and in_key in spec.keys(include_nested=True, leaves_only=True):
                return spec
        raise ValueError(
            f"{type(self).__name__}: the in_key {in_key!r} is declared neither in the reward spec "
            f"nor in the observation spec of the parent env "
            f"(reward keys: {list(parent.full_reward_spec.keys(True, True))}, observation keys: "
            f"{list(parent.full_observation_spec.keys(True, True))})."
        )

    def _generate_episode_reward_spec(self) -> Composite:
        # RewardSum's one builder of the sums' spec, read by its public transform_*_spec methods;
        # replacing it here keeps those methods (and their reward_spec switch) RewardSum's own.
        episode_spec = Composite()
        for in_key, out_key in zip(self.in_keys, self.out_keys, strict=True):
            source = self._source_spec(in_key)
            out_key = unravel_key(out_key)
            if isinstance(out_key, tuple):
                # Create the enclosing groups first, with the batch shape of the matching group of
                # the source spec (e.g. an agent group ``(*B, n_agents)``), or the source root's.
                node, src = episode_spec, source
                for sub_key in out_key[:-1]:
                    found = isinstance(src, Composite) and sub_key in src.keys()
                    src = src[sub_key] if found else None
                    if sub_key not in node.keys():
                        group = src if isinstance(src, Composite) else None
                        if group is None:
                            group = Composite(shape=source.shape, device=source.device)
                        node[sub_key] = group.empty()
                    node = node[sub_key]
            episode_spec[out_key] = source[in_key].clone()
        return episode_spec

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        keys = zip(self.in_keys, self.reset_keys, self.out_keys, strict=True)
        for in_key, reset_key, out_key in keys:
            value = tensordict.get(out_key, default=None)
            if value is None:
                value = self._source_spec(in_key)[in_key].zero()
            else:
                keep = ~_reset_flags(reset_key, tensordict)
                value = torch.where(expand_as_right(keep, value), value, 0.0)
            tensordict_reset.set(out_key, value)
        return tensordict_reset
