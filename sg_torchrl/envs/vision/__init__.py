"""Vision: pixel observations of the navigation envs (:mod:`.pixels`); vision-only scenes come later."""

from sg_torchrl.envs.vision.pixels import (
    DEFAULT_IMAGE_SIZE,
    OBS_MODES,
    ObservationContent,
    ObsMode,
    PixelObserver,
)

__all__ = ["DEFAULT_IMAGE_SIZE", "OBS_MODES", "ObservationContent", "ObsMode", "PixelObserver"]
