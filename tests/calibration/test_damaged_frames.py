"""Calibration never uses a damaged frame: an image that fails its recorded checksum is left out
of the background it detects against (and rejected as ``damaged image (checksum mismatch)`` where
the wand is detected). A real session file, damaged with h5py, read by the worker's own code."""

from __future__ import annotations

import shutil

import h5py
import numpy as np

from calibration.detect.background import temporal_median
from calibration.detect.worker import background_work
from protocol.images import decode_image
from tests.protocol.test_session import _raw, _write_session


def test_a_damaged_frame_is_left_out_of_the_background(tmp_path):
    clean = tmp_path / "clean.h5"
    _write_session(clean, rows=20)
    path = tmp_path / "damaged.h5"
    shutil.copy(clean, path)
    with h5py.File(path, "r+") as f:  # camera 103 records raw 8x4 images: row 12's right one
        g = f["cameras/103"]
        g["right_bytes"][int(g["right_offset"][12]) + 40] ^= 0x01
    serial, _, right = background_work((str(path), None, 103, np.array([10, 11, 12, 13, 14])))
    others = [decode_image(_raw(row + 1), "raw_bgr8", 8, 4) for row in (10, 11, 13, 14)]
    assert serial == 103 and np.array_equal(right, temporal_median(others))
