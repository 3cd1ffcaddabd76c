"""Navigation robots (Safety-Gymnasium paper, section 4.1). ``ROBOTS`` maps the name used in env ids to the robot class."""

from sg_torchrl.envs.navigation.robots.ant import Ant
from sg_torchrl.envs.navigation.robots.base import FIXED_SENSORS, Robot, SensorTerm
from sg_torchrl.envs.navigation.robots.car import Car
from sg_torchrl.envs.navigation.robots.doggo import Doggo
from sg_torchrl.envs.navigation.robots.point import Point
from sg_torchrl.envs.navigation.robots.racecar import Racecar

ROBOTS: dict[str, type[Robot]] = {cls.name: cls for cls in (Point, Car, Racecar, Doggo, Ant)}

__all__ = ["Ant", "Car", "Doggo", "FIXED_SENSORS", "ROBOTS", "Point", "Racecar", "Robot", "SensorTerm"]
