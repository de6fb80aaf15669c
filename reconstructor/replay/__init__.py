"""Reviewing a reconstructed case (docs/replay.md): ``egosurg replay`` (a path through space and
time to an MP4) and ``egosurg sightline`` (a target's visible fraction from a viewer, and from a
counterfactual position).

``path`` (a trajectory as a camera at any time), ``models`` (the case's models by time, checked
and preloaded in the background), ``video`` (H.264 MP4, time code, picture-in-picture), ``run``
(replay), ``sightline``, ``cli``.

Reads cases, never sessions' reconstruction (the session only for a picture-in-picture frame).
May import: protocol/, ``reconstructor.case`` (the index), ``data``, ``splats``, ``raster``,
``config``, ``errors``; never ``evaluation``, ``pipeline`` or ``cli``.
"""
