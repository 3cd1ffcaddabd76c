"""Vision: pixel observations of the navigation envs (:mod:`.pixels`).

The vision scenes are navigation tasks (``sg_torchrl.envs.navigation.tasks``): FadingEasy / FadingHard
(objects fading per simulator, :mod:`sg_torchrl.envs.navigation.fading`) and Race (a road with fixed
scenery, :mod:`sg_torchrl.envs.navigation.scenery`); Building and FormulaOne are not built yet.
"""

from sg_torchrl.envs.vision.pixels import (
    DEFAULT_IMAGE_SIZE,
    OBS_MODES,
    ObservationContent,
    ObsMode,
    PixelObserver,
)

__all__ = ["DEFAULT_IMAGE_SIZE", "OBS_MODES", "ObservationContent", "ObsMode", "PixelObserver"]
