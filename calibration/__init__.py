"""Extrinsic calibration of the four-camera rig with a three-sphere wand."""
