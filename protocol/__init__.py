"""Contracts shared by every part of EgoSurg, in wings:

- ``wire/``: the messages between agents, the recorder and the control tools (the byte-level
  spec is ``wire/__init__``'s docstring);
- ``session/``: the HDF5 session file, its writer and its readers (the facade is
  ``protocol.session``);
- ``formats/``: the files the parts exchange (camera tables, the rig calibration, the ZED factory
  file, evaluation sets, sites, trajectories, the wand);
- at the top, what all of them share: errors, the camera model, the image codec, the one way to
  read a TOML file into a typed config and write it back (``toml_config``, ``config_fields``),
  the one way to write a command (``command``), files that survive a crash (``durable``),
  files only their owner reads (``private_files``), the ``egosurg`` dispatcher.

protocol/ imports none of the other four packages. Its third-party needs are the edge's: numpy,
OpenCV (the camera model and the image codec), h5py and xxhash (the session file), pyzmq (the
wire's socket checks), tomli-w (writing TOML) and tomli on Python 3.10 (3.11 has tomllib). It
never imports torch, open3d, numba, scipy or matplotlib, so it runs on a Jetson node
(``tests/test_package_rules.py::test_the_edge_imports_without_heavy_libraries``).
"""

__version__ = "0.1.0"
