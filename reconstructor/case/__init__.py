"""A whole case, not an instant, as the unit of work: every timestamp of a session at an interval,
reconstructed into one folder that resumes after any interruption, here, in a pool of processes
or on a Ray cluster, optionally warm-started from the timestamp before (docs/case.md).

``plan`` (which timestamps), ``index`` (``case.json``), ``work`` (one timestamp in a worker),
``warm`` (warm start), ``runner`` (scheduling), ``ray_backend``, ``cli``.

May import: protocol/, ``reconstructor.data``, ``depth``, ``splats``, ``refine``, ``raster``,
``config``, ``pipeline``, ``errors``, ``plugins``; never ``evaluation`` (training does not
depend on its judge).
"""
