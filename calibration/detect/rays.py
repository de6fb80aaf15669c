"""Where the wand detector (``calibration.detect.detector``) samples across a sphere's outline:
the samples of a ray lie at ``OFFSETS`` around the expected edge, ``STEP`` px apart; ``WINDOW``
is where clipping or leaving the ROI matters, ``OUTSIDE`` where the background is read. The fast
kernels and the reference twins (``calibration.detect.kernels``, ``calibration.detect._reference``)
sample at the same places. ``outside_cone`` drops the edge points that leave along the wand's rod.
"""

from __future__ import annotations

import math

import numpy as np

STEP = 0.25  # px between samples along a ray
OFFSETS = np.arange(-3.0, 3.0 + 1e-9, STEP)  # samples relative to the expected edge
WINDOW = (OFFSETS >= -2.0) & (OFFSETS <= 3.0)  # where clipping or leaving the ROI matters
OUTSIDE = OFFSETS >= 2.0  # where the background is read


def outside_cone(
    edges: np.ndarray, centre: np.ndarray, axis: np.ndarray, half_angle_deg: float
) -> tuple[np.ndarray, float]:
    """Edge points not within ``half_angle_deg`` of ``±axis`` seen from ``centre``, and the
    fraction of the outline that leaves."""
    a = axis / max(float(np.linalg.norm(axis)), 1e-12)
    v = edges - centre
    cos = np.abs(v @ a) / np.maximum(np.linalg.norm(v, axis=1), 1e-12)
    keep = cos < math.cos(math.radians(half_angle_deg))
    return edges[keep], 1.0 - 2.0 * half_angle_deg / 180.0
