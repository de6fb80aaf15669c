"""Stereo depth and the fused point cloud: the matcher seam (``matcher.py``) and its loader
(``matchers.py``), the built-in SGBM+WLS matcher (``sgbm.py``), rectification and depth maps
(``stereo.py``), hole filling (``fill.py``) and fusion into one cloud (``fusion.py``).

May import: protocol/, ``reconstructor.data``, ``reconstructor.errors``, ``reconstructor.plugins``.
Never splats/, refine/ or evaluation/: depth knows nothing of Gaussians.
"""
