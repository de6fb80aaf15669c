"""The recorder (``egosurg recorder``): subscribes to every agent of the rig, groups their
frames into synchronised sets and writes one HDF5 session per take.

``recorder.py`` composes the parts its I/O thread changes and owns the loop. Each part has one
owner: ``intake`` (the camera table: each message an agent publishes, what was refused),
``links`` (the sockets and the agents' keys), ``disk`` (free space and the reserve), ``take``
(the take in progress, how it ends and whether a killed take resumes). Beside them: ``start``
(a take's checks and first write), ``status`` (the status reply), ``sync`` (grouping by capture
time), ``accounting`` (drops and gaps), ``recording`` (one take's file), ``write_queue`` (the
writer thread) and ``take_journal`` (resume after a kill). Imports run one way: no part imports
``recorder.py``."""
