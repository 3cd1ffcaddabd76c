"""Safe navigation tasks (Safety-Gymnasium paper, section 4.1): robots, objects, tasks, the world builder.

Layout of this package:

* ``world.py``   ``MjSpec`` world builder, compiled-model cache, :class:`Scene` (batched state views)
* ``robots/``    :class:`Robot` interface and the robots (``ROBOTS``)
* ``objects/``   :class:`NavObject` and the task objects (goal, constraints)
* ``tasks/``     :class:`Task` interface and the task classes
* ``compose.py`` :class:`TaskSpec`: a task declared as data (objective, extents, objects, reward), the
                 composition API of custom tasks and of the Goal, Button, Push and Circle levels
* ``levels.py``  every task's levels (``TASKS``; ``MULTI_AGENT_TASKS``: MultiGoal), what the registry reads
* ``fading.py``  per-simulator render alphas of fading objects (the Fading tasks)
* ``layout.py``  vectorised layout sampling with keep-outs
* ``scenery/``   static set dressing of a level (textured floor, fixed geoms: Race's village, Building's
                 construction site, FormulaOne's race track)
* ``track.py``   FormulaOne's race-track geometry (centre line, checkpoints, track-side positions)
* ``lidar.py``   vectorised pseudo-lidar
* ``env.py``     :class:`NavigationEnv`, the TorchRL env composing all of the above (its multi-agent
                 interface: :class:`sg_torchrl.envs.multi_agent.MultiAgentNavigationEnv`)
"""

from sg_torchrl.envs.navigation.env import NavigationEnv
from sg_torchrl.envs.navigation.objects import FreeObject, Goal, Hazards, NavObject, StaticObject, Vases
from sg_torchrl.envs.navigation.objects import CircleZone, Sigwalls
from sg_torchrl.envs.navigation.robots import ROBOTS, Ant, Car, Doggo, Point, Racecar, Robot
from sg_torchrl.envs.navigation.tasks import GoalTask, MultiGoalTask, Task
from sg_torchrl.envs.navigation.levels import MULTI_AGENT_TASKS, TASKS, make_task
from sg_torchrl.envs.navigation.compose import TaskSpec, TaskSpecError
from sg_torchrl.envs.navigation.tasks import CircleTask, RunTask
from sg_torchrl.envs.navigation.tasks import FadingEasyTask, FadingHardTask, FadingTask, RaceTask
from sg_torchrl.envs.navigation.fading import Fader
from sg_torchrl.envs.navigation.scenery import ConstructionSite, Prop, RaceTrackScenery, RoadSegment, Scenery, Village
from sg_torchrl.envs.navigation.objects import Buttons, GoalMarker, Gremlins, Pillars, PushBox
from sg_torchrl.envs.navigation.objects import AgentGoal, GoalBlue, GoalRed
from sg_torchrl.envs.navigation.tasks import ButtonTask, PushTask

__all__ = [
    "AgentGoal",
    "Ant",
    "ButtonTask",
    "Buttons",
    "GoalMarker",
    "Gremlins",
    "Pillars",
    "PushBox",
    "PushTask",
    "Car",
    "Doggo",
    "Fader",
    "FadingEasyTask",
    "FadingHardTask",
    "FadingTask",
    "Prop",
    "RaceTask",
    "RoadSegment",
    "Scenery",
    "Village",
    "ConstructionSite",
    "RaceTrackScenery",
    "CircleTask",
    "CircleZone",
    "FreeObject",
    "Goal",
    "GoalBlue",
    "GoalRed",
    "GoalTask",
    "MULTI_AGENT_TASKS",
    "MultiGoalTask",
    "Hazards",
    "NavObject",
    "NavigationEnv",
    "Point",
    "ROBOTS",
    "Racecar",
    "Robot",
    "RunTask",
    "Sigwalls",
    "StaticObject",
    "TASKS",
    "Task",
    "TaskSpec",
    "TaskSpecError",
    "Vases",
    "make_task",
]
