"""Camera models shared by sim/, calibration/ and reconstructor/.

Conventions (OpenCV throughout):
- camera frame: x right, y down, z forward; pixel (0, 0) is the centre of the top-left pixel;
- a pose is world-to-camera: ``x_cam = R @ x_world + t``, translation in metres;
- distortion is OpenCV's five-term Brown-Conrady model ``k1 k2 p1 p2 k3`` or its eight-term
  rational model ``k1 k2 p1 p2 k3 k4 k5 k6`` (``CALIB_RATIONAL_MODEL`` order, radial factor
  ``(1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)``). ZED factory files hold
  the five terms, and the rational ones where Stereolabs calibrated a ZED X lens with them; every
  OpenCV call that takes ``dist_array`` accepts either length.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import cast

import numpy as np

from protocol.errors import UserError


class ResolutionError(UserError, ValueError):
    """An unknown resolution name."""


class Resolution(enum.Enum):
    """The ZED X capture modes. The value is the name users type."""

    HD1200 = "HD1200"
    HD1080 = "HD1080"
    SVGA = "SVGA"

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return _SIZES[self]

    @property
    def width(self) -> int:
        return self.size[0]

    @property
    def height(self) -> int:
        return self.size[1]

    @property
    def conf_suffix(self) -> str:
        """Section suffix in a ZED ``SN<serial>.conf`` file."""
        return _CONF_SUFFIX[self]

    @property
    def max_fps(self) -> int:
        return 120 if self is Resolution.SVGA else 60

    @classmethod
    def parse(cls, name: str | Resolution) -> Resolution:
        """Accept ``"HD1200"``, ``"hd1200"`` or a ``Resolution``; reject anything else clearly."""
        if isinstance(name, Resolution):
            return name
        key = str(name).strip().upper()
        for res in cls:
            if res.value == key:
                return res
        valid = ", ".join(r.value for r in cls)
        raise ResolutionError(f"unknown resolution {name!r}; the ZED X modes are {valid}")


_SIZES = {
    Resolution.HD1200: (1920, 1200),
    Resolution.HD1080: (1920, 1080),
    Resolution.SVGA: (960, 600),
}
_CONF_SUFFIX = {Resolution.HD1200: "FHD1200", Resolution.HD1080: "FHD", Resolution.SVGA: "SVGA"}


# The lengths of OpenCV's distortion vectors this project uses: Brown-Conrady and rational.
DIST_TERMS = (5, 8)


@dataclass(frozen=True, kw_only=True)
class Intrinsics:
    """Pinhole intrinsics with OpenCV distortion, for one sensor at one resolution."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"image size must be positive, got {self.width_px}x{self.height_px}")
        if not (self.fx_px > 0 and self.fy_px > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx_px} fy={self.fy_px}")
        if len(self.dist) not in DIST_TERMS:
            raise ValueError(
                "dist must have 5 terms (k1 k2 p1 p2 k3) or 8 (k1 k2 p1 p2 k3 k4 k5 k6), "
                f"got {len(self.dist)}"
            )
        object.__setattr__(self, "dist", tuple(float(d) for d in self.dist))

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix."""
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]]
        )

    @property
    def dist_array(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=np.float64)

    @property
    def is_rational(self) -> bool:
        """Whether the lens uses the 8-term rational model (an 8-term ``dist``)."""
        return len(self.dist) == 8

    @property
    def dist8(self) -> tuple[float, ...]:
        """The distortion as 8 rational terms: a 5-term model is the rational one with
        k4 = k5 = k6 = 0 (the same radial factor, divided by 1)."""
        return (*self.dist, 0.0, 0.0, 0.0)[:8]

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    def undistorted(self) -> Intrinsics:
        """The same pinhole without distortion."""
        return replace(self, dist=(0.0, 0.0, 0.0, 0.0, 0.0))

    def shrunk(self, factor: int) -> Intrinsics:
        """The same pinhole, undistorted, for an image ``factor`` times smaller (integer sizes,
        rounded down; pixel centres at integer coordinates: x' = (x + 0.5) / factor - 0.5)."""
        if factor < 1:
            raise ValueError(f"factor must be at least 1, got {factor}")
        return Intrinsics(
            width_px=self.width_px // factor,
            height_px=self.height_px // factor,
            fx_px=self.fx_px / factor,
            fy_px=self.fy_px / factor,
            cx_px=(self.cx_px + 0.5) / factor - 0.5,
            cy_px=(self.cy_px + 0.5) / factor - 0.5,
        )

    @classmethod
    def from_fov(cls, width_px: int, height_px: int, hfov_deg: float) -> Intrinsics:
        """A centred, undistorted pinhole with the given horizontal field of view."""
        if not 1.0 < hfov_deg < 179.0:
            raise ValueError(f"hfov_deg must be between 1 and 179 degrees, got {hfov_deg}")
        fx = 0.5 * width_px / np.tan(np.radians(hfov_deg) / 2)
        return cls(
            width_px=width_px,
            height_px=height_px,
            fx_px=float(fx),
            fy_px=float(fx),
            cx_px=(width_px - 1) / 2,
            cy_px=(height_px - 1) / 2,
        )


@dataclass(frozen=True, kw_only=True)
class Pose:
    """A world-to-camera rigid transform: ``x_cam = R @ x_world + t`` (metres)."""

    R: np.ndarray
    t_m: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(self.t_m, dtype=np.float64).reshape(3)
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("R must be a proper rotation matrix")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t_m", t)

    @property
    def centre_m(self) -> np.ndarray:
        """The camera centre in world coordinates."""
        return -self.R.T @ self.t_m

    @property
    def matrix(self) -> np.ndarray:
        """4x4 world-to-camera matrix."""
        M = np.eye(4)
        M[:3, :3] = self.R
        M[:3, 3] = self.t_m
        return M

    def compose(self, other: Pose) -> Pose:
        """``self ∘ other``: apply ``other`` first, then ``self``."""
        return Pose(R=self.R @ other.R, t_m=self.R @ other.t_m + self.t_m)

    def inverse(self) -> Pose:
        return Pose(R=self.R.T, t_m=-self.R.T @ self.t_m)

    def transform(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 3) camera points."""
        return np.asarray(points_world) @ self.R.T + self.t_m

    @classmethod
    def look_at(cls, eye_m: np.ndarray, target_m: np.ndarray, up: np.ndarray | None = None) -> Pose:
        """A camera at ``eye_m`` looking at ``target_m``, image-up towards ``up`` (default +z)."""
        eye = np.asarray(eye_m, dtype=np.float64)
        fwd = np.asarray(target_m, dtype=np.float64) - eye
        norm = np.linalg.norm(fwd)
        if norm < 1e-9:
            raise ValueError("look_at needs a target distinct from the eye position")
        z = fwd / norm
        up_v = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
        x = np.cross(z, up_v)
        if np.linalg.norm(x) < 1e-6:  # looking straight up or down: pick any consistent right
            x = np.cross(z, np.array([0.0, 1.0, 0.0]))
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        return cls(R=R, t_m=-R @ eye)


@dataclass(frozen=True, kw_only=True)
class Camera:
    """A posed sensor: intrinsics plus a world-to-camera pose, and a name for messages."""

    name: str
    intrinsics: Intrinsics
    pose: Pose

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) world points -> ((N, 2) distorted pixels, (N,) depth Z in metres)."""
        import cv2  # local: keep protocol importable without OpenCV for tiny tools

        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        cam = self.pose.transform(pts)
        rvec, _ = cv2.Rodrigues(self.pose.R)
        px, _ = cv2.projectPoints(
            pts, rvec, self.pose.t_m, self.intrinsics.K, self.intrinsics.dist_array
        )
        return px.reshape(-1, 2), cam[:, 2]


def undistort_to_normalized(pixels: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(N, 2) distorted pixel coordinates -> (N, 2) normalized undistorted coordinates (x/z, y/z).

    Iterates to convergence (OpenCV's default stops after 5 iterations, which leaves up to
    ~0.1 px of error at the corners of a wide lens).
    """
    import cv2

    pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    if not intr.has_distortion:
        out = np.empty((len(pts), 2))
        out[:, 0] = (pts[:, 0, 0] - intr.cx_px) / intr.fx_px
        out[:, 1] = (pts[:, 0, 1] - intr.cy_px) / intr.fy_px
        return out
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)
    # R = P = identity is what OpenCV uses when they are not given: normalized coordinates out
    identity = np.eye(3)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
        und = cv2.undistortPointsIter(pts, intr.K, intr.dist_array, identity, identity, criteria)
    else:
        # OpenCV 5 folds the criteria into undistortPoints; the stubs installed with 4.x do not
        # know that signature, so it is typed here as what it returns.
        undistort_points = cast(Callable[..., np.ndarray], cv2.undistortPoints)
        und = undistort_points(pts, intr.K, intr.dist_array, criteria=criteria)
    return np.asarray(und).reshape(-1, 2)
