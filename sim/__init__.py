"""A simulated operating room with ground truth.

The simulator is a real camera source for the capture agent and the truth for every quality
number: four ZED X stereo rigs on the walls, an OR table with a patient, equipment, people who walk
and work through scripted workflow phases, and a three-sphere calibration wand.

Library use::

    from sim import World
    world = World.from_seed(7, phase="intraoperative")
    left, right = world.render_stereo(0, t_s=1.5, resolution="HD1200")
    left.image_rgb, left.depth_m          # uint8 (H, W, 3), float32 (H, W) metres
    world.head_poses(1.5)                  # egocentric ground-truth cameras

sim/ imports only protocol/: ground truth must not depend on what it judges.
"""

from sim.world import Render, World, WorldConfig

__all__ = ["Render", "World", "WorldConfig"]
