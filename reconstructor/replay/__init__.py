"""Reviewing a reconstructed case (docs/replay.md): ``egosurg replay`` (a path through space and
time to an MP4), ``egosurg sightline`` (a target's visible fraction from a viewer, and from a
counterfactual position), ``egosurg sterile`` (moving things entering a sterile field box) and
``egosurg view`` (the case in a web browser).

``path`` (a trajectory as a camera at any time), ``models`` (the case's models by time, checked
and preloaded in the background), ``video`` (H.264 MP4, time code, picture-in-picture), ``run``
(replay), ``sightline`` + ``sightline_run`` (line of sight), ``sterile`` + ``sterile_run`` (the
static scene, field-box contact events and their renders), ``observed`` + ``observed_case``
(observed versus inferred per pixel, and its use by replay and sightline), ``view`` +
``view_scene`` (the browser viewer and the conversions it is handed), ``view_boundary``
(which browser pages may connect: Origin, Host, token) + ``view_inputs`` (control values checked
before viser stores them), ``cli``.

Reads cases, never sessions' reconstruction (the session only for a picture-in-picture frame).
May import: protocol/, ``reconstructor.case`` (the index), ``data``, ``splats``, ``raster``,
``config``, ``errors``; never ``evaluation``, ``pipeline`` or ``cli``.
"""
