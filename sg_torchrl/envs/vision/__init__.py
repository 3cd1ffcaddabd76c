"""Vision: pixel observations of the navigation envs (:mod:`.pixels`) and Safety-Gymnasium's dict
layout of them (:mod:`.layout`).

The vision scenes are navigation tasks (``sg_torchrl.envs.navigation.tasks``): FadingEasy / FadingHard
(objects fading per simulator, :mod:`sg_torchrl.envs.navigation.fading`), Race (a village road),
BuildingGoal / BuildingButton / BuildingPush (a construction site) and FormulaOne (a race track); their
fixed set dressing is :mod:`sg_torchrl.envs.navigation.scenery`.
"""

from sg_torchrl.envs.vision.layout import DictEntry, DictLayout
from sg_torchrl.envs.vision.pixels import (
    DEFAULT_IMAGE_SIZE,
    OBS_MODES,
    ObservationContent,
    ObsMode,
    PixelObserver,
)

__all__ = ["DEFAULT_IMAGE_SIZE", "DictEntry", "DictLayout", "OBS_MODES", "ObservationContent", "ObsMode",
           "PixelObserver"]
