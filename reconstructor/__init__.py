"""Offline per-timestamp reconstruction of a recorded case into 3D Gaussian splats."""

from reconstructor.denormals import flush_denormals

# before any parallel operation starts worker threads, which copy the mode (see denormals.py)
flush_denormals()
