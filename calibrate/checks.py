"""Plausibility of a calibrated rig: results that are probably wrong are said, not silently used.

A rig whose translations are in millimetres (an aniposelib file imported without ``--scale-to-m``)
triangulates people kilometres away and ends with nobody found; one whose cameras all sit at one point
cannot triangulate at all. Rooms of the field span 2-30 m (Tanke ch. 8's kitchens about 10 m).
"""

from __future__ import annotations

import numpy as np

from roomcap.calibrate.camera import CameraRig

MAX_RIG_SPAN_M = 100.0  # wider than any room or hall: probably another unit
MIN_BASELINE_M = 0.02  # cameras closer than this cannot triangulate a room


def rig_span_m(rig: CameraRig) -> tuple[float, float]:
    """(largest, smallest) distance between two camera centres, in the rig's units (metres if right)."""
    c = rig.centers()
    if len(c) < 2:
        return 0.0, 0.0
    d = np.linalg.norm(c[:, None] - c[None], axis=-1)[np.triu_indices(len(c), 1)]
    return float(d.max()), float(d.min())


def rig_warnings(rig: CameraRig, source: str = "the rig") -> list[str]:
    """Sentences about what looks wrong with ``rig`` and what to do; empty when it looks like a room."""
    if len(rig) < 2:
        return []
    widest, closest = rig_span_m(rig)
    out = []
    if widest > MAX_RIG_SPAN_M:
        out.append(
            f"{source}: the cameras are {widest:,.0f} m apart ({widest / 1000:.1f} km), wider than any room: "
            "its translations are probably in millimetres or centimetres. Import the calibration again "
            "with --scale-to-m 0.001 (mm) or 0.01 (cm)."
        )
    if closest < MIN_BASELINE_M:
        out.append(
            f"{source}: two cameras are {closest * 1000:.1f} mm apart; triangulation between them is "
            "unreliable. Check the calibration (are the translations in metres?) or drop one camera."
        )
    return out
