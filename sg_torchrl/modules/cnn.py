"""The convolutional stack of the pixel networks, as plain data (no torch import).

It lives apart from :mod:`sg_torchrl.modules.mlp` so that ``sg-train`` can check an ``image_size``
against :data:`DEFAULT_CNN` while it validates the command line, before torch is loaded.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["CNNArchitecture", "DEFAULT_CNN"]


@dataclass(frozen=True)
class CNNArchitecture:
    """A convolutional stack: one ReLU ``Conv2d`` per entry of ``channels`` (no padding).

    The default, :data:`DEFAULT_CNN`, is the Nature-DQN stack (Mnih et al. 2015: kernels 8, 4, 3 and
    strides 4, 2, 1) with half its channels (16, 32, 32 instead of 32, 64, 64): on 64 x 64 images it
    ends at 32 x 4 x 4 = 512 features, and it trains about three times faster on a CPU core than the
    full-width stack, which matters when three of them (actor and two critics) learn every minibatch.
    """

    channels: tuple[int, ...] = (16, 32, 32)
    kernel_sizes: tuple[int, ...] = (8, 4, 3)
    strides: tuple[int, ...] = (4, 2, 1)

    def __post_init__(self) -> None:
        if not len(self.channels) == len(self.kernel_sizes) == len(self.strides) >= 1:
            raise ValueError("CNNArchitecture: channels, kernel_sizes and strides need one entry per layer")

    def output_side(self, side: int) -> int:
        """Side of the last feature map for a ``side``-pixel input (< 1: the image is too small)."""
        for kernel, stride in zip(self.kernel_sizes, self.strides):
            if side < kernel:
                return 0
            side = (side - kernel) // stride + 1
        return side

    @property
    def min_image_size(self) -> int:
        """The smallest image side the stack accepts (36 pixels for :data:`DEFAULT_CNN`)."""
        side = 1
        for kernel, stride in zip(reversed(self.kernel_sizes), reversed(self.strides)):
            side = (side - 1) * stride + kernel
        return side


DEFAULT_CNN = CNNArchitecture()
