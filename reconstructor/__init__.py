"""Offline per-timestamp reconstruction of a recorded case into 3D Gaussian splats.

By stage, each importing only the ones before it (docs/architecture.md): ``data`` (a set of
frames, training views) -> ``depth`` (stereo, fusion) -> ``splats`` (Gaussians, training; the
rasterizer is ``raster``) -> ``refine`` (auxiliary views, refiners), tied together by
``pipeline``; ``evaluation`` judges the result and nothing but the commands imports it.
"""

from reconstructor.splats.denormals import flush_denormals

# before any parallel operation starts worker threads, which copy the mode (see denormals.py)
flush_denormals()
