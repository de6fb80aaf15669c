"""Who stood where and looked where (``egosurg people``, docs/replay.md): people found in each
timestamp's stereo points, tracked through the case, and each track's head pose, written as the
trajectory file the review tools read; tracks named as roles by the reviewer.

``config`` (the settings, with units and reasons), ``sources`` (each timestamp's points, from a
case's stored points or a session's stereo depth), ``heightmap`` (the points as a top-height map
over the floor; ``reference`` is its slow twin), ``detect`` (heads: the top of a column with
shoulders below it, and which way the shoulders face), ``track`` (detections joined over time,
gaps kept), ``pose`` (each track's eye and gaze), ``output`` (the people file), ``names`` (tracks
named as roles, and suggestions), ``cli`` (the commands).

Geometry only: no weights, no colours for identity (staff wear the same scrubs), nothing from the
simulator.
"""
