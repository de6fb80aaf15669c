"""The refinement stage's auxiliary views (``auxiliary.py``) and the view refiners that correct
them: the seam (``base.py``), the guided refiner (``guided.py``), Difix3D (``difix.py``) and the
loader that picks one by name, plug-ins included (``refiners.py``).

May import: protocol/, ``reconstructor.data``, ``reconstructor.splats``, ``reconstructor.raster``,
``reconstructor.errors``, ``reconstructor.plugins``. Never depth/ or evaluation/.
"""
