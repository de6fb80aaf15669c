"""Counts over synchronised sets that every report of a session must agree on.

A camera is *missing in a set* when the set's member row for it is ``MISSING`` (-1): the set was
written to the session's ``/sets`` table without a frame of that camera. Only sets in the file
count: the partial windows a recording trims at its start and end (see
``capture_agent/recorder/recording.py``) are not sets of the take, so they are not counted either.

The stop summary (``Recording.finish``, also stored in ``/summary`` as ``summary_json``),
``SessionReader.summary()`` and ``egosurg session info`` all call ``missing_in_sets``; they
once disagreed because the stop summary counted the synchroniser's markers, trimmed windows
included.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

MISSING = -1  # a set's member row for a camera without a frame in it


def missing_in_sets(
    members: np.ndarray | Sequence[Sequence[int]], camera_serials: Sequence[int]
) -> dict[int, int]:
    """Per camera serial, the number of sets in ``members`` without a frame of that camera.

    ``members`` is (N, C): one row per set, one column per camera in ``camera_serials`` order,
    holding the camera's frame row or ``MISSING``; N may be 0.
    """
    serials = [int(s) for s in camera_serials]
    table = np.asarray(members, dtype=np.int64)
    if table.size == 0:
        return dict.fromkeys(serials, 0)
    if table.ndim != 2 or table.shape[1] != len(serials):
        raise ValueError(
            f"set members have shape {table.shape}, expected (sets, {len(serials)} cameras)"
        )
    counts = (table < 0).sum(axis=0)
    return {s: int(n) for s, n in zip(serials, counts, strict=True)}
