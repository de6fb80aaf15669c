"""The parts of ``bench/bench_capture.py`` (the script and its sections stay there): ``measure``
(constants, CPU and thread readings, ``RunResult``, the table printer), ``rigs`` (the sim rig
and the replay feeders), ``runs`` (one recording), ``limits`` (the raw limits of part 2) and
``report`` (each section's table)."""
