"""The recorder (``egosurg recorder``): subscribes to every agent of the rig, groups their
frames into synchronised sets and writes one HDF5 session per take.

``recorder.py`` composes the parts and owns the I/O loop; ``intake`` (each message an agent
publishes), ``start`` (a take's checks and first write), ``take`` (how a take ends and resumes),
``status`` (the status reply), ``sync`` (grouping by capture time), ``accounting`` (drops and gaps),
``recording`` (one take's file), ``write_queue`` (the writer thread) and ``take_journal`` (resume
after a kill) each own one piece."""
