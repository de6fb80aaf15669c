"""The trainer turns OpenCV's thread pool off while it steps, and gives it back after."""

from __future__ import annotations

import cv2
import pytest

from reconstructor.train import opencv_single_threaded


def test_opencv_runs_on_one_thread_inside_and_gets_its_threads_back_after() -> None:
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        with opencv_single_threaded():
            assert cv2.getNumThreads() == 1
        assert cv2.getNumThreads() == 2
        with pytest.raises(RuntimeError), opencv_single_threaded():
            raise RuntimeError("a failing step")
        assert cv2.getNumThreads() == 2
    finally:
        cv2.setNumThreads(before)
