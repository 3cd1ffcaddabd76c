"""Contact counting over MuJoCo C simulators: :class:`ContactCounting`, a part of
:class:`~sg_torchrl.envs.physics.MujocoBatch`.

Navigation tasks price contacts (vases, pillars, gremlins, buttons) and read which geoms touch the
robot. One pass over each simulator's active contacts answers that for every object at once; a
handful of contacts (the usual step) is counted in a Python loop, which is cheaper than ten array
operations and gives the same whole-number counts.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

__all__ = ["ContactCounting"]

# Up to this many contacts, contact_counts counts them in a Python loop (whole numbers: the same counts as
# its array path, which a one-simulator navigation step paid ~10 us for with one or two contacts).
_FEW_CONTACTS = 8


def _partner_counts(pairs: list[list[int]], mask: list[bool]) -> dict[int, float]:
    """``{geom: number of contacts between it and a geom of mask}`` from contact geom ``pairs``, counted in
    a Python loop (whole numbers, so any order gives the same floats); a pair of two masked geoms counts
    for both."""
    counts: dict[int, float] = {}
    for first, second in pairs:
        if mask[first]:
            counts[second] = counts.get(second, 0.0) + 1.0
        if mask[second]:
            counts[first] = counts.get(first, 0.0) + 1.0
    return counts


class ContactCounting:
    """Contact counts of the simulators ``self.datas`` of ``self.model`` (a mixin of :class:`MujocoBatch`)."""

    model: mujoco.MjModel
    num_sims: int
    datas: Sequence[mujoco.MjData]

    def count_contacts(self, geoms_a: np.ndarray, geoms_b: np.ndarray) -> np.ndarray:
        """Number of active contacts between a geom of set A and a geom of set B, per simulator.

        Args:
            geoms_a / geoms_b: ``(ngeom,)`` bool masks over the model's geoms.

        Returns:
            ``(N,)`` float counts (a contact between two geoms in both sets counts once).
        """
        counts = np.zeros(self.num_sims)
        for i, data in enumerate(self.datas):
            if data.ncon:
                pairs = data.contact.geom
                first, second = pairs[:, 0], pairs[:, 1]
                hits = (geoms_a[first] & geoms_b[second]) | (geoms_a[second] & geoms_b[first])
                counts[i] = np.count_nonzero(hits)
        return counts

    def contact_counts(self, geoms: np.ndarray) -> np.ndarray:
        """Per simulator and geom, the number of active contacts between that geom and a geom of ``geoms``.

        Args:
            geoms: ``(ngeom,)`` bool mask (e.g. the robot's geoms).

        Returns:
            ``(N, ngeom)`` float counts: one pass over the contacts answers "how often does each
            object touch the robot" for every object at once.
        """
        ngeom = self.model.ngeom
        counts = np.zeros((self.num_sims, ngeom))
        mask = None
        for i, data in enumerate(self.datas):
            ncon = data.ncon
            if 0 < ncon <= _FEW_CONTACTS:  # the usual case: a loop over a few pairs beats ten array operations
                if mask is None:
                    mask = geoms.tolist()
                row = counts[i]
                for geom, count in _partner_counts(data.contact.geom.tolist(), mask).items():
                    row[geom] = count
            elif ncon:
                pairs = data.contact.geom
                first, second = pairs[:, 0], pairs[:, 1]
                partners = np.concatenate([second[geoms[first]], first[geoms[second]]])
                if len(partners):
                    counts[i] = np.bincount(partners, minlength=ngeom)
        return counts

    def contact_counts_one(self, geoms: list[bool]) -> dict[int, float]:
        """:meth:`contact_counts` of simulator 0 as ``{geom: count}`` over the geoms with a contact, ``geoms``
        the mask as a list of bools.

        Why a second form: a one-simulator step reads a handful of counts (a goal button, the gremlins) and
        its contacts are one or two pairs; this is the same loop as :meth:`contact_counts`' few-contacts case
        (:func:`_partner_counts`, the same whole-number counts) without the ``(1, ngeom)`` array or the
        indexing of it, whatever the number of contacts.
        """
        return _partner_counts(self.datas[0].contact.geom.tolist(), geoms)  # no contacts: no pairs, {}
