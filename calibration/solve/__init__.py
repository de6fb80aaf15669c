"""The rig's poses from wand observations: ``solver.solve`` (told how by ``config``) runs the
stages: input ``checks``, the linear ``start`` (its maths in ``linear``), the ``bundle``
adjustment and the ``world_frame``; ``drift`` expresses a new calibration in an old one's frame
and says how far each camera moved."""
