"""Offline per-timestamp reconstruction of a recorded case into 3D Gaussian splats."""
