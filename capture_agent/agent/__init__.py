"""The capture agent (``egosurg agent``): the daemon on one Jetson node, its cameras and its PTP
state. ``agent.py`` is the daemon; ``ptp.py`` reads linuxptp's state."""
