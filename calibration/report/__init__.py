"""What a calibration run writes beside the calibration: the report's numbers (``stats``), its
pass/fail limits (``thresholds``) and ``verdict``, the HTML ``page`` with its ``plots``, and the
``exports`` for other tools (OpenCV YAML, COLMAP text, nerfstudio ``transforms.json``)."""
