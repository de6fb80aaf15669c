"""The left border's band that no matcher can answer, filled by its geometry.

In a rectified pair a left pixel at column ``x`` with disparity ``d`` is seen by the right camera
at ``x - d``; where ``x < d`` that is outside the right image, so the left image's first ``d``
columns of every row have no partner (3-4 % of the pixels of the real pairs in
``bench/stereo_pairs.py``). The checks leave them holes, and rightly, for no cost can be computed
there. Their depth is still well guessed from the row's first answer: the surface that answer
lies on continues to the image's border, and exactly the pixels left of ``d`` of it are the ones
the right camera cannot see.

``fill_left_border`` takes that guess only where the hole is the band the geometry predicts: the
row's first answer at column ``f`` with disparity ``d`` explains a hole ``[0, f)`` up to ``f <=
d + slack_px``. A hole much wider than its first answer's disparity holds pixels the right camera
does see but the matcher could not answer (a blank or a nearer surface's edge): those rows are
left alone (without this test 9 % of the Motorcycle pair's filled pixels were more than 2 px off,
a nearer object's disparity carried onto the background behind it; with it, 0.4 %).
"""

from __future__ import annotations

import numpy as np


def fill_left_border(disparity_px: np.ndarray, slack_px: float) -> np.ndarray:
    """(H, W) float32: ``disparity_px`` (NaN for holes) with each row's leading hole filled by the
    row's first answer ``d`` at the pixels ``x < d - 0.5`` (no partner in the right image), on
    the rows whose first answer is at a column ``f <= d + slack_px``."""
    disp = np.asarray(disparity_px, np.float32)
    answered = np.isfinite(disp)
    first = np.argmax(answered, axis=1)  # 0 where a row has no answer at all: nothing to fill
    d = disp[np.arange(disp.shape[0]), first]
    explained = (first > 0) & answered.any(axis=1) & (first <= d + slack_px)
    xs = np.arange(disp.shape[1])[None, :]
    fill = explained[:, None] & (xs < first[:, None]) & (xs < d[:, None] - 0.5)
    return np.where(fill, d[:, None], disp).astype(np.float32)
