"""What a reconstruction reads: one synchronised set of a session as calibrated frames
(``frames.py``) and the training views made from them (``views.py``).

May import: protocol/, ``reconstructor.errors``. Nothing else of the reconstructor.
"""
