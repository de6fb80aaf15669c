"""A stand-in for the ZED SDK's ``pyzed`` package, for tests on machines without a ZED X.

Only ``pyzed.sl`` exists, and only the part of its API that ``capture_agent/sources/zed_source.py``
uses; it replays PNG frames. Tests put ``tests/fakes`` first on ``sys.path`` to use it.
"""
