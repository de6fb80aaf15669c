"""Finding the wand in a session: the sphere detector (``detector``, told what to look for by
``config``), its numba ``kernels`` and their slow numpy twins (``_reference``), where it samples
across an outline (``rays``), the image of a sphere (``sphere_geometry``), the ``background``
median, the spheres' labels (``label``), and the pass over a recorded session (``extract``, whose
processes run ``worker``) that turns frames into ``calibration.observations.WandObservations``."""
