"""The safety constraints of the Shadow-Hand tasks: ``SafeJoint`` and ``SafeFinger``.

Safety-Gymnasium paper, section 4.4 ("Safe Isaac Gym", Figure 7): the dexterous-hand tasks come in
two safe variants that restrict how the forefinger may move, modelling a hand whose finger is
damaged or must not be strained.

* **SafeJoint**: the forefinger's abduction joint (the paper's "joint 4") must stay within
  [-10 deg, 10 deg] (its full range is [-20 deg, 20 deg]).
* **SafeFinger**: SafeJoint's constraint, and the forefinger's knuckle and middle flexion joints
  (the paper's joints 3 and 2, each with a range of [0 deg, 90 deg]) must stay within
  [22.5 deg, 67.5 deg].

Joint numbers: the paper uses Shadow's numbering (J1 distal ... J4 abduction); the
gymnasium-robotics model numbers the same joints from 0. The one table, :data:`PAPER_JOINTS`:

=========== ========================== ==================== ===================
paper joint what it moves              Shadow Robot name    model (this scene)
=========== ========================== ==================== ===================
4           forefinger abduction       FFJ4                 ``robot0:FFJ3``
3           knuckle (MCP) flexion      FFJ3                 ``robot0:FFJ2``
2           middle (PIP) flexion       FFJ2                 ``robot0:FFJ1``
=========== ========================== ==================== ===================

Cost source. The paper states the constraint on joint angles; SafePO's original code instead
tests the *normalised action* of the actuator driving the joint (the action in [-1, 1] that maps
to the joint's range): a cost when it leaves [-0.5, 0.5]. For these joints the two agree on the
position target: [-0.5, 0.5] of [-20 deg, 20 deg] is [-10 deg, 10 deg], and of [0 deg, 90 deg]
is [22.5 deg, 67.5 deg]. They differ in what is measured: ``"joints"`` (default) reads the angle
the joint actually reached (a joint pushed by the ball, or lagging its servo, is priced as it is),
``"actions"`` the commanded target. In the model the middle-flexion actuator ``A_FFJ1`` drives the
coupled middle+distal pair (tendon ``T_FFJ1c``); its joint angle is ``FFJ1``'s.

Both hands are checked: a step costs when either hand's forefinger leaves a range (each hand is a
damaged-hand replica of the other; the paper does not say which hand is constrained). The
multi-agent form charges each hand's violations to that hand's agent.

Note for SafeFinger: the hands' rest pose (flexion 0, plus 20 % reset noise, as Isaac Gym's
default joint positions) lies *below* 22.5 deg, so under ``"joints"`` the first steps of an
episode cost until the policy bends the forefinger into range; under ``"actions"`` a zero action
(the middle of each range) is safe from the first step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from sg_torchrl.envs.hands.scene import HandLayout

__all__ = ["CostSource", "JointRange", "PAPER_JOINTS", "SAFETY_VARIANTS", "JointRangeConstraint"]

CostSource = Literal["joints", "actions"]

#: The paper's forefinger joint number -> the gymnasium-robotics model's (unprefixed) joint name.
PAPER_JOINTS: dict[int, str] = {4: "FFJ3", 3: "FFJ2", 2: "FFJ1"}


@dataclass(frozen=True)
class JointRange:
    """A safe interval for one model joint, in radians; the cost fires strictly outside it."""

    joint: str
    low: float
    high: float


_ABDUCTION = JointRange(PAPER_JOINTS[4], np.deg2rad(-10.0), np.deg2rad(10.0))
_FLEXION = tuple(JointRange(PAPER_JOINTS[j], np.deg2rad(22.5), np.deg2rad(67.5)) for j in (3, 2))

#: Variant name -> ``{constraint name: the ranges it checks}`` (each constraint is one ``cost_info`` entry).
SAFETY_VARIANTS: dict[str, dict[str, tuple[JointRange, ...]]] = {
    "SafeJoint": {"forefinger_abduction": (_ABDUCTION,)},
    "SafeFinger": {"forefinger_abduction": (_ABDUCTION,), "forefinger_flexion": _FLEXION},
}


class JointRangeConstraint:
    """One named constraint: some joints of every hand must stay in their safe ranges.

    Args:
        name: the ``cost_info`` entry.
        ranges: the joints and their safe intervals (radians).
        hands: the scene's hands (all are checked).
        source: ``"joints"`` measures the joint angles in ``qpos``; ``"actions"`` the normalised
            action of each joint's actuator against the same interval mapped to [-1, 1].

    :meth:`__call__` returns, per simulator, the number of (hand, joint) pairs outside their range
    (``SafeEnv`` turns it into an indicator under its default ``cost_mode``); :meth:`per_hand` the
    same count per hand (the multi-agent form, one agent per hand).
    """

    def __init__(self, name: str, ranges: Sequence[JointRange], hands: Sequence[HandLayout], source: CostSource) -> None:
        if source not in ("joints", "actions"):
            raise ValueError(f"cost_source must be 'joints' or 'actions', got {source!r}")
        self.name = name
        self.source = source
        columns, lows, highs = [], [], []
        offset = 0
        for hand in hands:
            for joint_range in ranges:
                qpos = hand.qpos_index(joint_range.joint)
                if source == "joints":
                    columns.append(qpos)
                    lows.append(joint_range.low)
                    highs.append(joint_range.high)
                else:
                    # The actuator's control range (a joint-angle target) maps to the action interval [-1, 1].
                    actuator = hand.actuator_index(joint_range.joint)
                    lo, hi = hand.ctrl_low[actuator], hand.ctrl_high[actuator]
                    columns.append(offset + actuator)
                    lows.append(2.0 * (joint_range.low - lo) / (hi - lo) - 1.0)
                    highs.append(2.0 * (joint_range.high - lo) / (hi - lo) - 1.0)
            offset += len(hand.actuators)
        shape = (len(hands), len(ranges))  # one row per hand
        self._columns = np.asarray(columns).reshape(shape)
        self._low = np.asarray(lows).reshape(shape)
        self._high = np.asarray(highs).reshape(shape)

    def per_hand(self, qpos: np.ndarray, action: np.ndarray) -> np.ndarray:
        """Violations per simulator and hand, ``(N, H)`` float64, from ``qpos`` ``(N, nq)`` or the normalised ``action``."""
        values = (qpos if self.source == "joints" else action)[:, self._columns]
        return ((values < self._low) | (values > self._high)).sum(axis=2).astype(np.float64)

    def __call__(self, qpos: np.ndarray, action: np.ndarray) -> np.ndarray:
        """Violations per simulator, ``(N,)`` float64, summed over the hands."""
        return self.per_hand(qpos, action).sum(axis=1)
