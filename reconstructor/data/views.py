"""Training and evaluation views: undistorted pinhole images with their camera matrices.

The rasterizer draws an ideal pinhole camera, so each recorded (distorted) image is resampled
once to the same camera matrix without distortion. Pixels whose source falls outside the sensor
are marked invalid in ``mask`` and left out of the loss and the metrics.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from protocol.camera import Camera, Intrinsics, Pose


@dataclass(frozen=True)
class View:
    """One posed pinhole image. Tensors are float32 on the CPU."""

    name: str
    image: torch.Tensor  # (H, W, 3) in [0, 1]
    mask: torch.Tensor  # (H, W) 1 where the pixel holds image content
    viewmat: torch.Tensor  # (4, 4) world-to-camera, OpenCV axes
    K: torch.Tensor  # (3, 3)
    width_px: int
    height_px: int

    @property
    def pose(self) -> Pose:
        m = self.viewmat.double().numpy()
        return Pose(R=m[:3, :3], t_m=m[:3, 3])

    @property
    def intrinsics(self) -> Intrinsics:
        k = self.K.double().numpy()
        return Intrinsics(
            width_px=self.width_px,
            height_px=self.height_px,
            fx_px=float(k[0, 0]),
            fy_px=float(k[1, 1]),
            cx_px=float(k[0, 2]),
            cy_px=float(k[1, 2]),
        )

    @property
    def camera(self) -> Camera:
        return Camera(name=self.name, intrinsics=self.intrinsics, pose=self.pose)


def undistort(image_rgb: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Resample a distorted image to the same K without distortion; returns (image, valid mask)."""
    h, w = image_rgb.shape[:2]
    if (w, h) != (intr.width_px, intr.height_px):
        raise ValueError(
            f"image is {w}x{h} but its intrinsics are for {intr.width_px}x{intr.height_px}"
        )
    if not intr.has_distortion:
        return image_rgb, np.ones((h, w), dtype=bool)
    K = intr.K
    map_x, map_y = cv2.initUndistortRectifyMap(K, intr.dist_array, None, K, (w, h), cv2.CV_32FC1)
    out = cv2.remap(image_rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    valid = (map_x >= 0) & (map_x <= w - 1) & (map_y >= 0) & (map_y <= h - 1)
    return out, valid


def view_from_image(camera: Camera, image_rgb: np.ndarray, *, max_width_px: int = 0) -> View:
    """A training view from a recorded image and its calibrated camera.

    ``max_width_px`` > 0 downsamples larger images (area filter), scaling K to match.
    """
    img, valid = undistort(image_rgb, camera.intrinsics)
    intr = camera.intrinsics.undistorted()
    K = intr.K.copy()
    h, w = img.shape[:2]
    if max_width_px and w > max_width_px:
        scale = max_width_px / w
        nw, nh = max_width_px, round(h * scale)
        img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        valid = cv2.resize(valid.astype(np.uint8), (nw, nh), interpolation=cv2.INTER_NEAREST) > 0
        # pixel centres at integer coordinates: x' = (x + 0.5) * s - 0.5
        K[0, 0] *= nw / w
        K[1, 1] *= nh / h
        K[0, 2] = (K[0, 2] + 0.5) * nw / w - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * nh / h - 0.5
        w, h = nw, nh
    return View(
        name=camera.name,
        image=torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32) / 255.0),
        mask=torch.from_numpy(valid.astype(np.float32)),
        viewmat=torch.from_numpy(camera.pose.matrix.astype(np.float32)),
        K=torch.from_numpy(K.astype(np.float32)),
        width_px=w,
        height_px=h,
    )


# A viewer's own head and face lie nearer than this to their eye (the sim's eye sits 13 cm in front
# of the head's centre, 3 cm in front of the face). Renders from a person's eye leave out what is
# nearer, as 3DGS's rasteriser culls everything nearer than 0.2 m: the head's Gaussians, seen
# from inside, would blur the whole view.
EYE_NEAR_M = 0.2


def novel_view(camera: Camera) -> View:
    """A view with no image, for rendering only (image and mask are empty)."""
    intr = camera.intrinsics.undistorted()
    return View(
        name=camera.name,
        image=torch.zeros(0, 0, 3),
        mask=torch.zeros(0, 0),
        viewmat=torch.from_numpy(camera.pose.matrix.astype(np.float32)),
        K=torch.from_numpy(intr.K.astype(np.float32)),
        width_px=intr.width_px,
        height_px=intr.height_px,
    )
