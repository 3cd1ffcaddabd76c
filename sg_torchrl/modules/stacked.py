"""Seed-stacked networks: S independent copies of SafePO's actor and critics, run as one.

A *seed group* trains S independent runs in one process (DESIGN.md, "Many seeds in one process").
SafePO's networks (:mod:`sg_torchrl.modules.mlp`: tanh MLPs of [64, 64], a Gaussian actor with a
state-independent log-std, separate reward and cost critics) are so small that a gradient step is
per-operator overhead; stacking the S copies of each weight along a leading seed dimension turns S
steps into one step of batched matmuls (``torch.baddbmm``) at little more than the cost of one. The
stacked layers (:class:`StackedMLP`, the CNN encoders) are in :mod:`sg_torchrl.modules.stacked_layers`.

Nothing is shared between seeds: seed ``s``'s slice of every tensor is exactly the network seed
``s``'s single-seed run has. :meth:`StackedActorCritic.from_single` copies the modules that
:func:`~sg_torchrl.modules.mlp.make_actor_critics` builds after ``torch.manual_seed(seed)`` (the
``init`` stream, :func:`sg_torchrl.seeding.seed_torch`), so a seed starts from the same
initialisation as in the single-seed trainer, and
:meth:`StackedActorCritic.export_seed` / :meth:`StackedActorCritic.copy_seed_to` give a seed back as
those modules (checkpoints, evaluation, equivalence tests).

**Flat parameter groups.** The parameters of the actor (mean MLP and log-std) live as views in one
seed-major buffer :attr:`StackedActorCritic.flat_actor` of shape ``(S, P_actor)``, those of both
critics in :attr:`StackedActorCritic.flat_critics` ``(S, P_critics)``, and each buffer's ``.grad``
is a second buffer that the parameters' ``.grad`` views alias. Backward accumulates straight into
the flat gradients, so the per-seed gradient clip and the masked Adam of
:mod:`sg_torchrl.train.fused` act on two tensors instead of nineteen, and a seed is a row. The
parameters' strides therefore have a gap between seeds; build the module on its device and dtype
(``.to()`` works, and rebuilds the buffers, which an optimiser over the old ones no longer sees).

**Pixel observations.** With an image layout (:class:`~sg_torchrl.modules.mlp.ObservationLayout`)
each of the three networks is a :class:`~sg_torchrl.modules.stacked_layers.StackedEncodedMLP` (stacked CNN
encoder, then the stacked MLP), whose convolution weights sit in the same flat groups; the networks
then read a TensorDict of batch ``[S, B]`` (:meth:`StackedActorCritic.read_observation`) instead of a
tensor, and passes over a whole epoch's batch go in chunks (:attr:`StackedActorCritic.chunk_size`,
:func:`in_chunks`) so its ``uint8`` images are never converted to float at once.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale
from torch import Tensor, nn
from torchrl.data import TensorSpec
from torchrl.modules import MLP, ConvNet

from sg_torchrl.modules.gaussian import gaussian_log_prob
from sg_torchrl.modules.mlp import ObservationLayout, make_actor_critics
from sg_torchrl.modules.stacked_layers import StackedEncodedMLP, StackedMLP, linear_layers, only_submodule

__all__ = ["StackedActorCritic", "StackedMLP", "in_chunks", "quiet_layout_warning"]

def in_chunks(fn, obs: Tensor | TensorDictBase, chunk_size: int | None) -> tuple[Tensor, ...]:
    """``fn`` over the samples of ``obs`` (``(S, N, ...)``) ``chunk_size`` at a time, outputs joined on dim 1.

    ``fn`` returns a tuple of ``(S, n, ...)`` tensors; ``chunk_size`` ``None`` (flat vectors) makes one call.
    """
    size = obs.shape[1]
    if chunk_size is None or size <= chunk_size:
        return tuple(fn(obs))
    parts = [fn(obs[:, start : start + chunk_size]) for start in range(0, size, chunk_size)]
    return tuple(torch.cat(outputs, dim=1) for outputs in zip(*parts))


def _actor_parts(actor: nn.Module) -> tuple[nn.Module, AddStateIndependentNormalScale]:
    """The mean MLP and the log-std module of an actor built by ``make_actor``."""
    scale = only_submodule(actor, AddStateIndependentNormalScale)
    if scale.scale_mapping != "exp":
        raise ValueError(f"stacked actors use scale = exp(log_std); this actor maps with {scale.scale_mapping!r}")
    return only_submodule(actor, MLP), scale


@contextmanager
def quiet_layout_warning() -> Iterator[None]:
    """Silence autograd's one-time note that a parameter's gradient does not follow its layout.

    The flat buffers give every parameter a gap between seeds, and autograd's "gradient layout
    contract" then asks for contiguous gradients; accumulating into the strided views is correct
    (only a possible slow-down is warned about, which the flat optimiser step more than repays).
    The warning fires once per process; wrap the first backward pass in this.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="grad and param do not obey the gradient layout contract")
        yield


class StackedActorCritic(nn.Module):
    """S seeds' Gaussian actors and reward and cost critics, stacked and flattened into two groups.

    The actor is ``actor_mean`` (a :class:`StackedMLP`) plus ``log_std`` of shape ``(S, A)``, with
    ``scale = exp(log_std).clamp_min(scale_lb)`` as torchrl's ``AddStateIndependentNormalScale``
    computes it; ``critic`` and ``cost_critic`` are :class:`StackedMLP`\\ s with one output. Inputs
    are seed-major: ``obs`` of shape ``(S, B, obs_dim)``; with an image layout every network is a
    :class:`~sg_torchrl.modules.stacked_layers.StackedEncodedMLP` reading a TensorDict of batch ``[S, B]``.

    Args:
        num_seeds: S.
        obs_dim: the flat observation's size, or the :class:`~sg_torchrl.modules.mlp.ObservationLayout`
            of what the env emits (images: CNN encoders).
        action_dim: the action's size.
        hidden_sizes: hidden widths of all three networks.
        scale_lb: lower bound of the action standard deviation (torchrl's default ``1e-4``).
        device, dtype: where the parameters live.

    Attributes:
        flat_actor: ``(S, P_actor)`` buffer holding every actor parameter (its ``.grad`` holds their
            gradients).
        flat_critics: ``(S, P_critics)`` buffer of both critics (reward critic first).
    """

    def __init__(
        self,
        num_seeds: int,
        obs_dim: int | ObservationLayout,
        action_dim: int,
        hidden_sizes: Sequence[int],
        *,
        scale_lb: float = 1e-4,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        options = dict(device=device, dtype=dtype)
        layout = obs_dim if isinstance(obs_dim, ObservationLayout) else ObservationLayout(vector_dim=int(obs_dim))
        #: What the networks read: the flat vector, or images (and the vector) through CNN encoders.
        self.layout = layout

        def network(out: int) -> StackedMLP | StackedEncodedMLP:
            if layout.images:
                return StackedEncodedMLP(num_seeds, layout, out, hidden_sizes, **options)
            return StackedMLP(num_seeds, layout.vector_dim, out, hidden_sizes, **options)

        self.actor_mean = network(action_dim)
        self.log_std = nn.Parameter(torch.zeros(num_seeds, action_dim, **options))
        self.critic = network(1)
        self.cost_critic = network(1)
        self.scale_lb = float(scale_lb)
        self._flatten()

    # ------------------------------------------------------------------ shape
    @property
    def num_seeds(self) -> int:
        return self.actor_mean.num_seeds

    @property
    def chunk_size(self) -> int | None:
        """Samples per no-grad pass over a whole batch (:func:`in_chunks`): ``None`` (all) for flat vectors."""
        return self.layout.chunk_size

    def read_observation(self, source: TensorDictBase, prefix: tuple[str, ...] = ()) -> Tensor | TensorDictBase:
        """What the networks read from ``source`` (batch ``[S * n, ...]``, seed-major), per seed: ``(S, N, ...)``.

        The ``(S, N, obs_dim)`` flat vector, or with images a TensorDict of batch ``[S, N]`` holding the
        layout's entries (views of ``source``'s: the images stay ``uint8``). ``prefix``: e.g. ``("next",)``.
        """
        seeds, dims = self.num_seeds, source.batch_dims

        def per_seed(value: Tensor) -> Tensor:
            return value.reshape(seeds, -1, *value.shape[dims:])

        if not self.layout.images:
            return per_seed(source.get((*prefix, "observation")))
        entries = {key: per_seed(source.get((*prefix, key))) for key in self.layout.in_keys}
        return TensorDict(entries, batch_size=next(iter(entries.values())).shape[:2])

    @property
    def action_dim(self) -> int:
        return self.actor_mean.sizes[-1]

    @property
    def hidden_sizes(self) -> tuple[int, ...]:
        return self.actor_mean.hidden_sizes

    # ------------------------------------------------------------------ flat groups
    def actor_parameters(self) -> list[nn.Parameter]:
        """The actor's parameters in flat-buffer order: mean MLP layer by layer, then ``log_std``."""
        return [*_net_params(self.actor_mean), self.log_std]

    @property
    def flat_groups(self) -> tuple[Tensor, Tensor]:
        """``(flat_actor, flat_critics)``: the optimiser's two tensors."""
        return self.flat_actor, self.flat_critics

    def _flatten(self) -> None:
        """Move every parameter into its group's flat buffer (as a view) and alias the gradients."""
        self.flat_actor = self._flatten_group(
            [(self.actor_mean, name) for name in self.actor_mean.parameter_names()] + [(self, "log_std")]
        )
        self.flat_critics = self._flatten_group(
            [(net, name) for net in (self.critic, self.cost_critic) for name in net.parameter_names()]
        )
        #: The reward critic's columns of ``flat_critics`` (they come first; the cost critic's follow).
        self.reward_critic_width = sum(p[0].numel() for p in _net_params(self.critic))

    @staticmethod
    def _flatten_group(slots: list[tuple[nn.Module, str]]) -> Tensor:
        params = [_get(module, name) for module, name in slots]
        first = params[0]
        seeds = first.shape[0]
        widths = [p[0].numel() for p in params]
        flat = torch.empty(seeds, sum(widths), device=first.device, dtype=first.dtype)
        flat.grad = torch.zeros_like(flat)
        offset = 0
        for (module, name), param, width in zip(slots, params, widths):
            view = flat[:, offset : offset + width].view(param.shape)
            view.copy_(param.detach())
            new = nn.Parameter(view, requires_grad=param.requires_grad)
            new.grad = flat.grad[:, offset : offset + width].view(param.shape)
            _set(module, name, new)
            offset += width
        return flat

    def _apply(self, fn, recurse: bool = True):
        # .to() / .double() convert each parameter on its own, which would cut them from the flat
        # buffers: convert, then rebuild the buffers around the converted values.
        super()._apply(fn, recurse)
        self._flatten()
        return self

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Zero both flat gradient buffers in place (the ``.grad`` views follow), whatever ``set_to_none`` says.

        Setting a parameter's ``.grad`` to ``None`` would cut it from the flat gradient buffer (the
        next backward would store a fresh tensor that the optimiser never reads).
        """
        self.flat_actor.grad.zero_()
        self.flat_critics.grad.zero_()

    @torch.no_grad()
    def critic_squared_norms(self) -> tuple[Tensor, Tensor]:
        """Per seed, the sum of squares of the reward critic's and of the cost critic's parameters, ``(S,)`` each."""
        width, flat = self.reward_critic_width, self.flat_critics
        return flat[:, :width].pow(2).sum(1), flat[:, width:].pow(2).sum(1)

    # ------------------------------------------------------------------ networks
    def scale(self) -> Tensor:
        """The action standard deviation, ``(S, 1, A)`` (broadcasts over the batch)."""
        return self.log_std.exp().clamp_min(self.scale_lb).unsqueeze(1)

    def dist_params(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """``(loc, scale)`` of each seed's policy: ``loc`` ``(S, B, A)``, ``scale`` ``(S, 1, A)``."""
        return self.actor_mean(obs), self.scale()

    def actor_rows(self, rows: Tensor) -> StackedActorCritic:
        """A group of this one's shape holding copies of the actor rows ``rows`` (its critics are zeros).

        What a trust-region step evaluates a subset of seeds in (its line search once some seeds
        have stopped, a seed group's live seeds), with :meth:`dist_params`' own forward pass.
        """
        weight = self.flat_actor
        part = StackedActorCritic(rows.numel(), self.layout, self.action_dim, self.hidden_sizes,
                                  scale_lb=self.scale_lb, device=weight.device, dtype=weight.dtype)
        with torch.no_grad():
            part.flat_actor.copy_(weight.index_select(0, rows))
        return part

    def values(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """Reward and cost values of ``obs``, ``(S, B)`` each."""
        return self.critic(obs).squeeze(-1), self.cost_critic(obs).squeeze(-1)

    @torch.no_grad()
    def sample(
        self, obs: Tensor, generators: Sequence[torch.Generator], *, deterministic: bool = False
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Actions for ``obs`` (``(S, B, obs_dim)``, or :meth:`read_observation`'s TensorDict), seed ``s``'s noise drawn from ``generators[s]``.

        Each seed draws ``randn(B, A)`` from its own generator, so its random stream (and, for the
        same weights and observations, its actions) is the same whatever the group size. The
        noise is drawn on each generator's device and moved to the networks' in one copy: a trainer's
        generators are CPU ones on every device, so its run draws the same numbers on a GPU as on the CPU.

        Returns:
            ``(action, log_prob, loc, scale)``: ``(S, B, A)``, ``(S, B)``, ``(S, B, A)``,
            ``(S, B, A)`` (``scale`` expanded, as the collector stores it). ``deterministic``
            returns the mean and draws nothing.
        """
        if len(generators) != self.num_seeds:
            raise ValueError(f"expected {self.num_seeds} generators (one per seed), got {len(generators)}")
        loc, scale = self.dist_params(obs)
        scale = scale.expand_as(loc)
        if deterministic:
            action = loc
        else:
            batch, dim = loc.shape[1:]
            noise = torch.stack([torch.randn(batch, dim, generator=g, device=g.device, dtype=loc.dtype)
                                 for g in generators])
            noise = noise.to(loc.device, non_blocking=True)
            action = loc + scale * noise
        return action, gaussian_log_prob(action, loc, scale), loc, scale

    # ------------------------------------------------------------------ single-seed modules
    @classmethod
    def from_single(
        cls, networks: Sequence[tuple[nn.Module, nn.Module, nn.Module]], *, layout: ObservationLayout | None = None,
        device: torch.device | str | None = None,
    ) -> StackedActorCritic:
        """Stack the ``(actor, critic, cost_critic)`` of S single-seed runs (``make_actor_critics``'s output).

        Seed ``s`` of the result holds copies of ``networks[s]``'s weights, so building each triple
        after ``torch.manual_seed(seed_s)`` (:func:`sg_torchrl.seeding.seed_torch`) gives every seed its
        single-seed initialisation. ``layout``: what the networks read; needed for networks with a
        CNN encoder (flat-vector networks tell their input size themselves).
        """
        if not networks:
            raise ValueError("from_single needs at least one (actor, critic, cost_critic)")
        mean0, scale0 = _actor_parts(networks[0][0])
        layers = linear_layers(mean0)
        weight = layers[0].weight
        hidden = [lin.out_features for lin in layers[:-1]]
        encoded = any(isinstance(m, ConvNet) for m in networks[0][0].modules())
        if layout is None:
            if encoded:
                raise ValueError("networks with a CNN encoder: give their ObservationLayout (layout=...)")
            layout = ObservationLayout(vector_dim=layers[0].in_features)
        elif encoded != layout.images:
            raise ValueError(f"the networks {'have' if encoded else 'lack'} a CNN encoder; the layout reads "
                             f"{layout.in_keys}")
        stacked = cls(len(networks), layout, layers[-1].out_features, hidden,
                      scale_lb=float(scale0.scale_lb), device=device or weight.device, dtype=weight.dtype)
        for seed, triple in enumerate(networks):
            stacked.load_seed(seed, *triple)
        return stacked

    @torch.no_grad()
    def load_seed(self, seed: int, actor: nn.Module, critic: nn.Module, cost_critic: nn.Module) -> None:
        """Copy single-seed modules (as ``make_actor_critics`` builds them) into seed ``seed``."""
        _, scale = _actor_parts(actor)
        if float(scale.scale_lb) != self.scale_lb:
            raise ValueError(f"scale lower bound {scale.scale_lb} differs from the group's {self.scale_lb}")
        for net, module in ((self.actor_mean, actor), (self.critic, critic), (self.cost_critic, cost_critic)):
            net.load_seed(seed, module if isinstance(net, StackedEncodedMLP) else only_submodule(module, MLP))
        self.log_std[seed].copy_(scale.state_independent_scale.detach())

    @torch.no_grad()
    def copy_seed_to(self, seed: int, actor: nn.Module, critic: nn.Module, cost_critic: nn.Module) -> None:
        """Write seed ``seed``'s weights into single-seed modules (e.g. for evaluation or a checkpoint)."""
        _, scale = _actor_parts(actor)
        for net, module in ((self.actor_mean, actor), (self.critic, critic), (self.cost_critic, cost_critic)):
            net.copy_seed_to(seed, module if isinstance(net, StackedEncodedMLP) else only_submodule(module, MLP))
        scale.state_independent_scale.copy_(self.log_std[seed])

    def export_seed(self, seed: int, action_spec: TensorSpec, device: torch.device | str | None = None
                    ) -> tuple[nn.Module, nn.Module, nn.Module]:
        """Seed ``seed`` as fresh single-seed ``(actor, critic, cost_critic)`` from ``make_actor_critics``.

        The modules are built without touching the global RNG state (their random initialisation is
        overwritten at once), on ``device`` (default: this group's; a trainer exports to the CPU for its
        checkpoints and evaluation).
        """
        with torch.random.fork_rng(devices=[]):
            triple = make_actor_critics(self.layout, action_spec, list(self.hidden_sizes))
        weight = self.flat_actor
        triple = tuple(module.to(weight.device if device is None else device).to(weight.dtype) for module in triple)
        self.copy_seed_to(seed, *triple)
        return triple


def _net_params(net: StackedMLP | StackedEncodedMLP) -> list[nn.Parameter]:
    return [_get(net, name) for name in net.parameter_names()]


def _get(module: nn.Module, name: str) -> nn.Parameter:
    return module.get_parameter(name)


def _set(module: nn.Module, name: str, param: nn.Parameter) -> None:
    *path, leaf = name.split(".")
    owner = module
    for part in path:
        owner = getattr(owner, part)
    if isinstance(owner, nn.ParameterList):
        owner[int(leaf)] = param
    else:
        setattr(owner, leaf, param)
