"""SafePO's actor and critics as TorchRL modules, reading the flat observation vector or pixels.

SafePO's ``ActorVCritic`` (the networks behind the paper's single-agent results): a Gaussian
actor whose mean is a tanh MLP and whose log-std is a state-independent parameter initialised to
0, plus separate reward and cost value MLPs of the same shape (no sharing). PyTorch's default
``Linear`` initialisation, as SafePO.

Pixel observations (an env built with ``obs_mode`` ``"rgb"``, ``"rgbd"``, ``"vector+rgb"`` or
``"vector+rgbd"``, e.g. every ``...Vision-v0`` id): what the networks read is worked out from the
env's observation spec (:class:`ObservationLayout`), so nothing needs configuring. Each network
then starts with its own :class:`ObservationEncoder`, a small convolutional stack
(:data:`DEFAULT_CNN`, TorchRL's :class:`~torchrl.modules.ConvNet`) over the images whose flattened
output is concatenated with the flat vector (when there is one), followed by the same tanh MLP as
above. The actor and the two critics do not share their encoder: SafePO's networks share nothing,
and a shared encoder would let the critics' regression targets move the policy's features (and the
cost critic's those of the reward critic) through one optimiser step. The price is three
convolutional stacks to train instead of one; only the actor runs during collection.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale
from torch import Tensor, nn
from torchrl.data import Composite, TensorSpec
from torchrl.modules import MLP, ConvNet, IndependentNormal, ProbabilisticActor

from sg_torchrl.modules.cnn import DEFAULT_CNN, CNNArchitecture
from sg_torchrl.modules.direct import DirectTensorDictModule, DirectValueOperator

__all__ = [
    "DEPTH_RANGE", "IMAGE_CHUNK", "EncodedMLP", "ObservationEncoder", "ObservationLayout",
    "forward_in_chunks", "image_channels", "make_actor", "make_actor_critics", "make_network", "make_value",
    "write_values",
]

#: Depth (metres) at which the encoder's depth channel saturates: ``min(depth, DEPTH_RANGE) / DEPTH_RANGE``.
#: Everything a navigation robot's camera sees lies within about 5 m (the arena); pixels that see
#: nothing read the far clipping plane (about 42 m), which this maps to 1 like the farthest wall.
DEPTH_RANGE = 5.0
#: Samples per no-grad forward pass when a network runs over a whole epoch's batch of images (GAE's
#: values, the KL early stop): a 20,000-image batch in float32 is about 1 GB per network before its
#: first convolution, so it is never converted at once.
IMAGE_CHUNK = 1024


@dataclass(frozen=True)
class ObservationLayout:
    """Which observation entries the networks read, and their sizes.

    Attributes:
        vector_dim: length of the flat ``"observation"`` vector, ``None`` when the env emits none.
        image_shape: ``(H, W)`` of the ``"pixels"`` / ``"depth"`` images, ``None`` without images.
        rgb: whether ``"pixels"`` (``uint8`` ``(H, W, 3)``, channels last as the envs emit it) is read.
        depth: whether ``"depth"`` (``float32`` ``(H, W, 1)``, metres) is read.
    """

    vector_dim: int | None
    image_shape: tuple[int, int] | None = None
    rgb: bool = False
    depth: bool = False

    @classmethod
    def from_spec(cls, observation_spec: Composite) -> ObservationLayout:
        """The layout of an env's ``observation_spec`` (the flat vector, ``pixels``, ``depth``)."""
        keys = set(observation_spec.keys())
        vector_dim = int(observation_spec["observation"].shape[-1]) if "observation" in keys else None
        for key, channels in (("pixels", 3), ("depth", 1)):
            shape = tuple(observation_spec[key].shape) if key in keys else None
            if shape is not None and (len(shape) < 3 or shape[-1] != channels):
                raise ValueError(f"{key!r} has shape {shape}: the encoders read TorchRL's channels-last images "
                                 f"(..., H, W, {channels}) as the envs emit them (not after ToTensorImage)")
        shapes = [tuple(observation_spec[key].shape[-3:-1]) for key in ("pixels", "depth") if key in keys]
        if len(set(shapes)) > 1:
            raise ValueError(f"'pixels' and 'depth' differ in size: {shapes}")
        layout = cls(vector_dim, shapes[0] if shapes else None, rgb="pixels" in keys, depth="depth" in keys)
        if not layout.in_keys:
            raise ValueError(f"the observation spec holds nothing the networks can read (keys {sorted(keys)}; "
                             f"expected 'observation', 'pixels' or 'depth')")
        return layout

    @property
    def images(self) -> bool:
        """Whether the networks read images (and so start with a CNN encoder)."""
        return self.rgb or self.depth

    @property
    def in_keys(self) -> list[str]:
        """The entries read, in the order the networks take them: ``pixels``, ``depth``, ``observation``."""
        flags = {"pixels": self.rgb, "depth": self.depth, "observation": self.vector_dim is not None}
        return [key for key, present in flags.items() if present]

    @property
    def chunk_size(self) -> int | None:
        """Samples per no-grad pass over a whole batch: :data:`IMAGE_CHUNK` with images, else all (``None``)."""
        return IMAGE_CHUNK if self.images else None


class ObservationEncoder(nn.Module):
    """Images (and the flat vector) to one feature vector: CNN features, then the vector, concatenated.

    ``pixels`` (``uint8``) are scaled to ``[0, 1]`` and ``depth`` to ``min(depth, depth_range) /
    depth_range`` inside the forward pass, so batches keep their compact ``uint8`` images and only
    the slice a call sees is converted to float. RGB and depth are stacked as input channels (3 + 1)
    of one :class:`~torchrl.modules.ConvNet`, whose flattened output is concatenated with the flat
    vector (normalised upstream by the trainer's running normaliser, as in vector-only training).
    The images come channels last (TorchRL's raw-pixel layout, ``(..., H, W, C)``); the encoder
    moves the channels first with a view, no copy: the result has PyTorch's ``channels_last`` memory
    format, which ``Conv2d`` takes as it is.

    Args:
        layout: what the env emits; must hold images.
        cnn: the convolutional stack.
        depth_range: metres at which the depth channel saturates.

    Attributes:
        out_features: length of the feature vector.
    """

    def __init__(
        self, layout: ObservationLayout, cnn: CNNArchitecture = DEFAULT_CNN, depth_range: float = DEPTH_RANGE
    ) -> None:
        super().__init__()
        if not layout.images:
            raise ValueError("ObservationEncoder needs image observations ('pixels' and/or 'depth')")
        sides = [cnn.output_side(side) for side in layout.image_shape]
        if min(sides) < 1:
            raise ValueError(f"images of {layout.image_shape[0]} x {layout.image_shape[1]} pixels are too small for "
                             f"the CNN encoder (kernels {cnn.kernel_sizes}, strides {cnn.strides}): it needs at "
                             f"least {cnn.min_image_size} pixels a side (env option image_size)")
        if not depth_range > 0:
            raise ValueError(f"depth_range must be > 0, got {depth_range}")
        self.in_keys = layout.in_keys
        self.depth_range = float(depth_range)
        self.cnn = ConvNet(in_features=3 * layout.rgb + layout.depth, num_cells=list(cnn.channels),
                           kernel_sizes=list(cnn.kernel_sizes), strides=list(cnn.strides), activation_class=nn.ReLU)
        self.out_features = cnn.channels[-1] * sides[0] * sides[1] + (layout.vector_dim or 0)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        """``inputs`` in :attr:`in_keys` order (``pixels``, ``depth``, ``observation``, those present);
        images channels last, ``(..., H, W, C)``."""
        entries = dict(zip(self.in_keys, inputs))
        images = image_channels(entries.get("pixels"), entries.get("depth"), self.depth_range)
        features = self.cnn(images.movedim(-1, -3))  # (..., H, W, C) -> (..., C, H, W), a view
        if "observation" in entries:
            features = torch.cat([features, entries["observation"]], dim=-1)
        return features


def image_channels(pixels: Tensor | None, depth: Tensor | None, depth_range: float) -> Tensor:
    """The encoders' float input channels, channels last: ``pixels / 255``, then ``depth`` as
    ``min(depth, depth_range) / depth_range``. Each is converted in one new tensor (the ``uint8`` input is
    untouched); at least one must be given.
    """
    channels = []
    if pixels is not None:
        channels.append(pixels / 255.0)
    if depth is not None:
        channels.append(depth.clamp(0.0, depth_range).div_(depth_range))
    return channels[0] if len(channels) == 1 else torch.cat(channels, dim=-1)


class EncodedMLP(nn.Module):
    """An :class:`ObservationEncoder` followed by a tanh MLP head: one network over images (and vector)."""

    def __init__(self, encoder: ObservationEncoder, out_features: int, hidden_sizes: Sequence[int]) -> None:
        super().__init__()
        self.encoder = encoder
        self.head = MLP(in_features=encoder.out_features, out_features=out_features, num_cells=list(hidden_sizes),
                        activation_class=nn.Tanh)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.head(self.encoder(*inputs))


class _Chain(nn.Sequential):
    """``nn.Sequential`` whose first module takes several inputs (the observation entries)."""

    def forward(self, *inputs: torch.Tensor):
        first, *rest = self
        output = first(*inputs)
        for module in rest:
            output = module(output)
        return output


def _layout(observation: int | Composite | ObservationLayout) -> ObservationLayout:
    if isinstance(observation, ObservationLayout):
        return observation
    if isinstance(observation, Composite):
        return ObservationLayout.from_spec(observation)
    if isinstance(observation, int) and not isinstance(observation, bool) and observation >= 1:
        return ObservationLayout(vector_dim=observation)
    raise TypeError(f"observation: expected a vector length, an observation spec or an ObservationLayout, "
                    f"got {observation!r}")


def make_network(
    observation: int | Composite | ObservationLayout, out_features: int, hidden_sizes: Sequence[int]
) -> nn.Module:
    """A tanh MLP over the flat vector, or (with images) an :class:`EncodedMLP` with its own CNN encoder.

    ``observation``: the flat vector's length, the env's observation spec, or its layout. The network
    takes the entries of ``ObservationLayout.in_keys`` as positional inputs.
    """
    layout = _layout(observation)
    if layout.images:
        return EncodedMLP(ObservationEncoder(layout), out_features, hidden_sizes)
    return MLP(in_features=layout.vector_dim, out_features=out_features, num_cells=list(hidden_sizes),
               activation_class=nn.Tanh)


def make_actor(
    observation: int | Composite | ObservationLayout, action_spec: TensorSpec, hidden_sizes: Sequence[int]
) -> ProbabilisticActor:
    """Gaussian policy writing ``loc``, ``scale``, ``action`` and ``action_log_prob``."""
    layout = _layout(observation)
    action_dim = int(action_spec.shape[-1])
    body = _Chain(
        make_network(layout, action_dim, hidden_sizes),
        AddStateIndependentNormalScale(action_dim, scale_mapping="exp", init_value=0.0),
    )
    return ProbabilisticActor(
        DirectTensorDictModule(body, in_keys=layout.in_keys, out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=action_spec,
        distribution_class=IndependentNormal,
        return_log_prob=True,
        default_interaction_type="random",
    )


def make_value(
    observation: int | Composite | ObservationLayout, hidden_sizes: Sequence[int], out_key: str
) -> DirectValueOperator:
    """A state-value network (tanh MLP, after a CNN encoder with images) writing ``out_key``."""
    layout = _layout(observation)
    return DirectValueOperator(make_network(layout, 1, hidden_sizes), in_keys=layout.in_keys, out_keys=[out_key])


def make_actor_critics(
    observation: int | Composite | ObservationLayout, action_spec: TensorSpec, hidden_sizes: Sequence[int]
) -> tuple[ProbabilisticActor, DirectValueOperator, DirectValueOperator]:
    """Actor, reward critic (``state_value``) and cost critic (``cost_value``), sharing no parameters.

    ``observation``: the env's ``observation_spec`` (what it emits decides between MLPs and CNN
    encoders), an :class:`ObservationLayout`, or the flat vector's length.
    """
    layout = _layout(observation)
    return (
        make_actor(layout, action_spec, hidden_sizes),
        make_value(layout, hidden_sizes, "state_value"),
        make_value(layout, hidden_sizes, "cost_value"),
    )


@torch.no_grad()
def forward_in_chunks(
    module: Callable[[TensorDictBase], TensorDictBase],
    data: TensorDictBase,
    in_keys: Sequence[NestedKey],
    out_keys: Sequence[NestedKey],
    chunk_size: int | None,
) -> dict[NestedKey, Tensor]:
    """``module``'s ``out_keys`` over the flat ``data``, computed ``chunk_size`` samples at a time.

    Only ``in_keys`` are handed to ``module`` (nothing else of the batch is copied); ``chunk_size``
    ``None`` runs the whole batch in one call. Networks over images use chunks so that the float
    copy of a whole epoch of ``uint8`` frames (and its first feature maps) never exists at once.
    """
    inputs = data.select(*in_keys)
    size = inputs.numel()
    step = size if chunk_size is None else max(int(chunk_size), 1)
    outputs = [module(inputs[start : start + step]) for start in range(0, size, step)]
    return {key: torch.cat([out.get(key) for out in outputs]) for key in out_keys}


@torch.no_grad()
def write_values(batch: TensorDictBase, critics: Sequence[nn.Module], chunk_size: int | None) -> None:
    """Each critic's value of the observations and of the next observations, written into ``batch``.

    ``batch`` is an epoch's ``(N, T)`` rollout; it is viewed flat and each critic (a value operator
    with one out-key, e.g. ``state_value``) runs ``chunk_size`` samples at a time
    (:func:`forward_in_chunks`), writing ``key`` and ``("next", key)``: what TorchRL's ``GAE`` reads
    when it has no value network of its own (its own would run on the observations and next
    observations stacked, all at once).
    """
    flat = batch.reshape(-1)
    for prefix, source in (((), flat), (("next",), flat.get("next"))):
        for critic in critics:
            key = critic.out_keys[0]
            values = forward_in_chunks(critic, source, critic.in_keys, [key], chunk_size)[key]
            batch.set((*prefix, key), values.reshape(*batch.shape, *values.shape[1:]))
