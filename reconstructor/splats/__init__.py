"""The Gaussians and their training: the model (``gaussians.py``), its PLY file (``ply.py``),
the trainer (``train.py``) with its image loss (``image_loss.py``, ``ssim.py``), and the CPU's
denormal setting the trainer needs (``denormals.py``). The rasterizer is ``reconstructor.raster``.

May import: protocol/, ``reconstructor.data``, ``reconstructor.raster``, ``reconstructor.errors``.
Never depth/ (the pipeline hands points over), refine/ or evaluation/.
"""
