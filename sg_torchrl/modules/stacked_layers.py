"""Seed-stacked networks: S copies of SafePO's tanh MLPs and of the pixel networks' CNN encoders, run as one.

:class:`StackedMLP` stacks S tanh MLPs (one ``baddbmm`` per layer for all seeds).
The pixel networks of :mod:`sg_torchrl.modules.mlp` (a CNN encoder over the images, the flat
vector appended, then SafePO's tanh MLP) are stacked as :class:`StackedEncodedMLP`. Layer ``i`` of S seeds' convolutional
stacks is one weight ``(S, out_i, in_i, k_i, k_i)`` and one bias ``(S, out_i)`` (so the convolutions
sit in the group's flat parameter buffers like every other weight), and the forward pass runs one
``conv2d`` per seed on its slice: exactly the call its own :class:`~torchrl.modules.ConvNet` makes, so
each seed's features are its single network's bit for bit. Unlike the MLPs, convolutions are not
per-operator overhead: on a CPU core (S = 3, 64 images of 64 x 64 x 4, forward and backward) the loop
over seeds takes 13 ms, one grouped ``Conv2d`` (``groups=S`` over ``(B, S * C, H, W)``) 18 ms and
``torch.func.vmap`` 34 ms.

Observations of an image layout travel as a TensorDict of batch ``[S, N]`` (what
:meth:`~sg_torchrl.modules.stacked.StackedActorCritic.read_observation` builds) holding ``"pixels"``
(``uint8``, channels last, as the envs emit them), ``"depth"`` (metres) and ``"observation"`` (the
flat vector), those the layout reads; the images are converted to float inside the forward pass,
so batches keep them in ``uint8``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn
from torch.nn import functional as F
from torchrl.modules import MLP, ConvNet

from sg_torchrl.modules.cnn import DEFAULT_CNN, CNNArchitecture
from sg_torchrl.modules.mlp import DEPTH_RANGE, ObservationLayout, image_channels

__all__ = [
    "StackedConvNet", "StackedEncodedMLP", "StackedEncoder", "StackedMLP", "conv_layers", "linear_layers",
    "only_submodule", "stacked_mlp_forward",
]


def linear_layers(mlp: nn.Module) -> list[nn.Linear]:
    """The ``Linear`` layers of a tanh MLP (``Linear``, ``Tanh``, ..., ``Linear``), checked."""
    children = list(mlp.children()) if isinstance(mlp, nn.Sequential) else []
    shapes_ok = len(children) % 2 == 1 and all(
        isinstance(child, nn.Linear if i % 2 == 0 else nn.Tanh) for i, child in enumerate(children)
    )
    if not shapes_ok or not all(child.bias is not None for child in children[::2]):
        raise TypeError(f"expected a tanh MLP (Linear, Tanh, ..., Linear, with biases), got {mlp}")
    return children[::2]


def stacked_mlp_forward(x: Tensor, layers: Iterable[tuple[Tensor, Tensor]],
                        activation: Callable[[Tensor], Tensor]) -> Tensor:
    """Many MLPs at once: ``x`` ``(R, B, in)`` through ``layers`` of ``(R, in_i, out_i)`` weights (``nn.Linear``'s
    transposed) and ``(R, 1, out_i)`` biases, ``activation`` between layers and none after the last; row ``r``
    only sees its own weights. The one stacked forward pass (tanh seed groups, ReLU off-policy networks)."""
    layers = list(layers)
    for i, (weight, bias) in enumerate(layers):
        x = torch.baddbmm(bias, x, weight)
        if i < len(layers) - 1:
            x = activation(x)
    return x


class StackedMLP(nn.Module):
    """S independent tanh MLPs whose layers are stacked along a leading seed dimension.

    Layer ``i`` is ``weights[i]`` of shape ``(S, in_i, out_i)`` (the transpose of ``nn.Linear``'s
    ``(out, in)``, so the forward pass is ``baddbmm(bias, x, weight)`` without a transpose) and
    ``biases[i]`` of shape ``(S, 1, out_i)``; tanh between layers, none after the last, as
    torchrl's ``MLP(activation_class=nn.Tanh)``. Build it with :meth:`from_modules`; the
    constructor leaves zeros.

    Args:
        num_seeds: S.
        in_features, out_features: input and output sizes.
        hidden_sizes: widths of the hidden layers.
        device, dtype: where the parameters live.
    """

    def __init__(
        self,
        num_seeds: int,
        in_features: int,
        out_features: int,
        hidden_sizes: Sequence[int],
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        if num_seeds < 1:
            raise ValueError(f"num_seeds must be >= 1, got {num_seeds}")
        sizes = [int(in_features), *map(int, hidden_sizes), int(out_features)]
        options = dict(device=device, dtype=dtype)
        self.weights = nn.ParameterList(
            [nn.Parameter(torch.zeros(num_seeds, a, b, **options)) for a, b in zip(sizes[:-1], sizes[1:])]
        )
        self.biases = nn.ParameterList([nn.Parameter(torch.zeros(num_seeds, 1, b, **options)) for b in sizes[1:]])
        self.num_seeds = int(num_seeds)
        self.sizes = tuple(sizes)

    @property
    def hidden_sizes(self) -> tuple[int, ...]:
        return self.sizes[1:-1]

    def forward(self, x: Tensor) -> Tensor:
        """``x`` of shape ``(S, B, in)`` to ``(S, B, out)``; seed ``s`` only sees its own weights."""
        return stacked_mlp_forward(x, zip(self.weights, self.biases), torch.tanh)

    @classmethod
    def from_modules(
        cls, modules: Sequence[nn.Module], *, device: torch.device | str | None = None
    ) -> StackedMLP:
        """Stack S tanh MLPs of one shape (e.g. torchrl ``MLP``\\ s), copying each one's weights."""
        if not modules:
            raise ValueError("from_modules needs at least one module")
        layers = [linear_layers(module) for module in modules]
        shapes = {tuple((lin.in_features, lin.out_features) for lin in seed) for seed in layers}
        if len(shapes) != 1:
            raise ValueError(f"the modules differ in shape: {sorted(shapes)}")
        first = layers[0]
        sizes = [first[0].in_features, *(lin.out_features for lin in first)]
        weight = first[0].weight
        stacked = cls(len(modules), sizes[0], sizes[-1], sizes[1:-1], device=device or weight.device,
                      dtype=weight.dtype)
        for seed, module in enumerate(modules):
            stacked.load_seed(seed, module)
        return stacked

    def _paired_layers(self, module: nn.Module) -> Iterable[tuple[nn.Linear, Tensor, Tensor]]:
        """``(Linear, weights, biases)`` per layer of a single tanh MLP of this shape."""
        layers = linear_layers(module)
        if len(layers) != len(self.weights):
            raise ValueError(f"expected {len(self.weights)} Linear layers, got {len(layers)}")
        return zip(layers, self.weights, self.biases)

    @torch.no_grad()
    def load_seed(self, seed: int, module: nn.Module) -> None:
        """Copy the weights of a single tanh MLP of this shape into seed ``seed``'s slice."""
        for linear, weight, bias in self._paired_layers(module):
            weight[seed].copy_(linear.weight.detach().T)
            bias[seed, 0].copy_(linear.bias.detach())

    @torch.no_grad()
    def copy_seed_to(self, seed: int, module: nn.Module) -> nn.Module:
        """Write seed ``seed``'s weights into a single tanh MLP of this shape; returns it."""
        for linear, weight, bias in self._paired_layers(module):
            linear.weight.copy_(weight[seed].T)
            linear.bias.copy_(bias[seed, 0])
        return module

    def export(self, seed: int) -> MLP:
        """Seed ``seed`` as a fresh torchrl ``MLP`` (what ``make_network`` builds), with its weights."""
        weight = self.weights[0]
        mlp = MLP(in_features=self.sizes[0], out_features=self.sizes[-1], num_cells=list(self.hidden_sizes),
                  activation_class=nn.Tanh, device=weight.device)
        return self.copy_seed_to(seed, mlp.to(weight.dtype))

    def parameter_names(self) -> list[str]:
        """Parameter names in flat-buffer order: layer by layer, weight then bias."""
        return [f"{kind}.{i}" for i in range(len(self.weights)) for kind in ("weights", "biases")]


def conv_layers(net: nn.Module) -> list[nn.Conv2d]:
    """The ``Conv2d`` layers of a ReLU ConvNet (``Conv2d``, ``ReLU``, ..., ``SquashDims``), checked."""
    convs = [m for m in net.modules() if isinstance(m, nn.Conv2d)]
    if not convs or any(c.bias is None or c.groups != 1 or c.padding != (0, 0) or c.dilation != (1, 1)
                        for c in convs):
        raise TypeError(f"expected a ConvNet of unpadded Conv2d layers with biases, got {net}")
    return convs


class StackedConvNet(nn.Module):
    """S ReLU ConvNets (no padding, ReLU after every layer, flattened) stacked along a leading seed dimension.

    Args:
        num_seeds: S.
        in_channels: input channels per seed.
        cnn: the stack (channels, kernels, strides).
        device, dtype: where the parameters live.
    """

    def __init__(self, num_seeds: int, in_channels: int, cnn: CNNArchitecture = DEFAULT_CNN, *,
                 device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> None:
        super().__init__()
        options = dict(device=device, dtype=dtype)
        sizes = [int(in_channels), *cnn.channels]
        self.weights = nn.ParameterList([nn.Parameter(torch.zeros(num_seeds, b, a, k, k, **options))
                                         for a, b, k in zip(sizes[:-1], sizes[1:], cnn.kernel_sizes)])
        self.biases = nn.ParameterList([nn.Parameter(torch.zeros(num_seeds, b, **options)) for b in sizes[1:]])
        self.strides = tuple(cnn.strides)
        self.num_seeds = int(num_seeds)

    def forward(self, images: Tensor) -> Tensor:
        """Float ``images`` ``(S, B, H, W, C)`` (channels last) to flattened features ``(S, B, F)``.

        The features of each seed are flattened as ``ConvNet``'s ``SquashDims`` flattens them (channels, rows,
        columns).
        """
        features = []
        for seed in range(images.shape[0]):
            x = images[seed].movedim(-1, 1)  # channels first as a view (channels_last memory), as ObservationEncoder
            for weight, bias, stride in zip(self.weights, self.biases, self.strides):
                x = F.relu(F.conv2d(x, weight[seed], bias[seed], stride=stride))
            features.append(x.flatten(1))
        return torch.stack(features)

    @torch.no_grad()
    def load_seed(self, seed: int, net: nn.Module) -> None:
        """Copy a single ConvNet of this shape into seed ``seed``'s slice."""
        for conv, weight, bias in zip(conv_layers(net), self.weights, self.biases, strict=True):
            weight[seed].copy_(conv.weight)
            bias[seed].copy_(conv.bias)

    @torch.no_grad()
    def copy_seed_to(self, seed: int, net: nn.Module) -> None:
        """Write seed ``seed``'s weights into a single ConvNet of this shape."""
        for conv, weight, bias in zip(conv_layers(net), self.weights, self.biases, strict=True):
            conv.weight.copy_(weight[seed])
            conv.bias.copy_(bias[seed])


class StackedEncoder(nn.Module):
    """S :class:`~sg_torchrl.modules.mlp.ObservationEncoder` s: the images scaled as there, a
    :class:`StackedConvNet`, the flat vector appended.

    Args:
        num_seeds: S.
        layout: what the env emits (must hold images).
        cnn, depth_range: as :class:`~sg_torchrl.modules.mlp.ObservationEncoder`.
        device, dtype: where the parameters live.
    """

    def __init__(self, num_seeds: int, layout: ObservationLayout, cnn: CNNArchitecture = DEFAULT_CNN,
                 depth_range: float = DEPTH_RANGE, *, device: torch.device | str | None = None,
                 dtype: torch.dtype | None = None) -> None:
        super().__init__()
        if not layout.images:
            raise ValueError("StackedEncoder needs image observations ('pixels' and/or 'depth')")
        self.layout, self.depth_range = layout, float(depth_range)
        self.conv = StackedConvNet(num_seeds, 3 * layout.rgb + layout.depth, cnn, device=device, dtype=dtype)
        sides = [cnn.output_side(side) for side in layout.image_shape]
        self.out_features = cnn.channels[-1] * sides[0] * sides[1] + (layout.vector_dim or 0)

    def forward(self, obs: TensorDictBase) -> Tensor:
        """``obs`` of batch ``[S, B]`` (the layout's entries) to features ``(S, B, out_features)``."""
        layout = self.layout
        features = self.conv(image_channels(obs.get("pixels") if layout.rgb else None,
                                            obs.get("depth") if layout.depth else None, self.depth_range))
        if layout.vector_dim is not None:
            features = torch.cat([features, obs.get("observation")], dim=-1)
        return features


class StackedEncodedMLP(nn.Module):
    """S :class:`~sg_torchrl.modules.mlp.EncodedMLP` s: a :class:`StackedEncoder`, then a stacked tanh MLP head.

    Args:
        num_seeds: S.
        layout: what the env emits (must hold images).
        out_features, hidden_sizes: the head's output size and hidden widths.
        device, dtype: where the parameters live.
    """

    def __init__(self, num_seeds: int, layout: ObservationLayout, out_features: int, hidden_sizes: Sequence[int], *,
                 device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> None:
        super().__init__()
        self.encoder = StackedEncoder(num_seeds, layout, device=device, dtype=dtype)
        self.head = StackedMLP(num_seeds, self.encoder.out_features, out_features, hidden_sizes,
                               device=device, dtype=dtype)

    @property
    def num_seeds(self) -> int:
        return self.head.num_seeds

    @property
    def sizes(self) -> tuple[int, ...]:
        return self.head.sizes

    @property
    def hidden_sizes(self) -> tuple[int, ...]:
        return self.head.hidden_sizes

    def parameter_names(self) -> list[str]:
        """Parameter names in flat-buffer order: the convolutions layer by layer, then the head's."""
        conv = self.encoder.conv
        names = [f"encoder.conv.{kind}.{i}" for i in range(len(conv.weights)) for kind in ("weights", "biases")]
        return names + ["head." + name for name in self.head.parameter_names()]

    def forward(self, obs: TensorDictBase) -> Tensor:
        return self.head(self.encoder(obs))

    def load_seed(self, seed: int, network: nn.Module) -> None:
        """Copy a single encoded network (its one ``ConvNet`` and one ``MLP``) into seed ``seed``."""
        self.encoder.conv.load_seed(seed, only_submodule(network, ConvNet))
        self.head.load_seed(seed, only_submodule(network, MLP))

    def copy_seed_to(self, seed: int, network: nn.Module) -> None:
        """Write seed ``seed``'s weights into a single encoded network of this shape."""
        self.encoder.conv.copy_seed_to(seed, only_submodule(network, ConvNet))
        self.head.copy_seed_to(seed, only_submodule(network, MLP))


def only_submodule(module: nn.Module, kind: type) -> nn.Module:
    """The one sub-module of ``module`` (itself included) of type ``kind``; a ``TypeError`` unless exactly one."""
    found = [m for m in module.modules() if isinstance(m, kind)]
    if len(found) != 1:
        raise TypeError(f"expected exactly one {kind.__name__} in {type(module).__name__}, found {len(found)}")
    return found[0]
