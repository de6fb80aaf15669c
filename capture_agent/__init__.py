"""The edge half of EgoSurg: capture agents on the Jetson nodes and the recorder.

Imports neither torch nor open3d, so it runs on a small node (docs/architecture.md).
"""
