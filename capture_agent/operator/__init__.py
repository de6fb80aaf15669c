"""What an operator runs against a rig: ``egosurg record`` / ``status`` (``control``), the console
(``console``), the control-socket client (``rig_client``), ``egosurg keys`` and
``egosurg session``."""
