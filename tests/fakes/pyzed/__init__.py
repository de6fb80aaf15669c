"""A stand-in for the ZED SDK's ``pyzed`` package, for tests on machines without a ZED X.

Only ``pyzed.sl`` exists (as ZED SDK 5.x behaves), and only the part of its API that the agent
uses; it replays PNG frames. Tests put ``tests/fakes`` first on ``sys.path`` to use it.
"""
