"""Navigation robots. ``ROBOTS`` maps the name used in env ids to the robot class."""

from sg_torchrl.envs.navigation.robots.base import FIXED_SENSORS, Robot, SensorTerm
from sg_torchrl.envs.navigation.robots.car import Car
from sg_torchrl.envs.navigation.robots.point import Point

ROBOTS: dict[str, type[Robot]] = {cls.name: cls for cls in (Point, Car)}

__all__ = ["Car", "FIXED_SENSORS", "ROBOTS", "Point", "Robot", "SensorTerm"]
