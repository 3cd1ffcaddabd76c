"""The :class:`Scenery` interface and the helpers every scenery uses (floor texture, daylight)."""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.objects.contacts import robot_contacts

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.world import Scene

__all__ = ["FloorTexture", "Scenery", "daylight"]

RGB = Sequence[float]


@dataclass(frozen=True)
class FloorTexture:
    """A built-in 2-D MuJoCo texture (``builtin``, two colours, optional random marks) on the world's
    ``floor`` geom, tiled ``repeat`` times across it; the texture is named ``name``, its material
    ``<name>_material``. The floor's colour becomes white so the texture shows its own colours."""

    name: str
    builtin: mujoco.mjtBuiltin
    rgb1: tuple[float, float, float]
    rgb2: tuple[float, float, float]
    mark: mujoco.mjtMark = mujoco.mjtMark.mjMARK_NONE
    markrgb: tuple[float, float, float] = (0.0, 0.0, 0.0)
    random: float = 0.0
    repeat: float = 4.0
    size: int = 128

    def apply(self, spec: mujoco.MjSpec) -> None:
        spec.add_texture(name=self.name, type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=self.builtin,
                         rgb1=list(self.rgb1), rgb2=list(self.rgb2), mark=self.mark, markrgb=list(self.markrgb),
                         random=self.random, width=self.size, height=self.size)
        material = spec.add_material(name=f"{self.name}_material", texrepeat=[self.repeat, self.repeat],
                                     reflectance=0.0)
        material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = self.name
        floor = spec.geom("floor")
        floor.material = material.name
        floor.rgba = [1.0, 1.0, 1.0, 1.0]


def daylight(spec: mujoco.MjSpec, name: str, strength: float = 0.45) -> None:
    """Add a directional light that lights the whole floor evenly (the world's own light is a spot
    above the origin, which leaves a large scene's edges dark)."""
    spec.worldbody.add_light(name=name, type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, dir=[0.3, 0.4, -1.0],
                             castshadow=False, diffuse=[strength] * 3, specular=[0.0, 0.0, 0.0])


class Scenery(abc.ABC):
    """Static set dressing of one task level (see :mod:`~sg_torchrl.envs.navigation.scenery`).

    A subclass names its :attr:`prefix`, sets :attr:`floor` (and :attr:`light` for a large scene),
    and adds its geoms in :meth:`add_geoms`; :attr:`key` lists what those depend on. :meth:`build`
    does the rest, the same way for every scenery. A task that charges robot contacts with the solid
    scenery (Race) calls :meth:`bind` once the model is compiled, then :meth:`robot_contacts`.
    """

    #: name prefix of the scenery's light (``<prefix>_daylight``)
    prefix: ClassVar[str]
    #: the floor's texture (``None``: the world's plain grey floor)
    floor: FloorTexture | None = None
    #: strength of an extra directional light (``None``: none; the world's spot light only)
    light: ClassVar[float | None] = None

    @property
    @abc.abstractmethod
    def key(self) -> tuple:
        """What :meth:`build` depends on (part of the compiled-model cache key)."""

    @abc.abstractmethod
    def add_geoms(self, world: mujoco.MjsBody) -> None:
        """Add the scenery's fixed geoms to the ``world`` body."""

    def build(self, spec: mujoco.MjSpec) -> None:
        """Restyle the floor, add the light and the scenery's geoms to the world ``spec``."""
        if self.floor is not None:
            self.floor.apply(spec)
        if self.light is not None:
            daylight(spec, f"{self.prefix}_daylight", self.light)
        self.add_geoms(spec.worldbody)

    def bind(self, model: mujoco.MjModel) -> None:
        """Resolve the solid scenery geoms in the compiled model: the world body's colliding geoms
        other than the floor (task objects and robots have bodies of their own)."""
        #: ``(ngeom,)`` bool, the scenery's colliding geoms
        self.geom_mask = (model.geom_bodyid == 0) & ((model.geom_contype != 0) | (model.geom_conaffinity != 0))
        self.geom_mask[model.geom("floor").id] = False

    def robot_contacts(self, scene: Scene) -> np.ndarray:
        """Number of contacts between the (scene's) robot and the solid scenery, ``(N,)`` (after :meth:`bind`)."""
        return robot_contacts(scene, self.geom_mask)
