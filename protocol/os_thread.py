"""Naming the calling thread for the operating system, so ``top -H``, ``ps -L`` and
``/proc/<pid>/task/<tid>/comm`` show what each of a daemon's threads is (Python 3.11 names its
threads for itself only)."""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
import threading

_PR_SET_NAME = 15  # prctl(2)
_libc = (
    ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True) if sys.platform == "linux" else None
)


def name_os_thread(name: str) -> bool:
    """Give the calling thread ``name`` (cut to the kernel's 15 bytes); False where not Linux."""
    if _libc is None:
        return False
    return _libc.prctl(_PR_SET_NAME, name.encode()[:15], 0, 0, 0) == 0


class NamedThread(threading.Thread):
    """A ``threading.Thread`` whose ``name`` the operating system sees too."""

    def run(self) -> None:
        name_os_thread(self.name)
        super().run()
