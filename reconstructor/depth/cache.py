"""The depth stage's results (stereo depth per camera and the fused cloud), kept once per
timestamp and configuration.

Every row of an evaluation, and every warm-started frame, starts from the same stereo depth and
fused cloud of a timestamp; ``DepthCache`` computes them once. With a folder it also keeps them
on disk (``egosurg evaluate --depth-cache DIR``), so that a rerun with other training settings
skips stereo and fusion, and so that a machine without OpenCV's contrib modules or open3d (the
lent GPU machines) can train from depth made elsewhere.

A stored entry is keyed by an xxh3-128 digest of everything the stage reads: each sensor's
image bytes, its calibration, and the resolved stereo, fill and fusion settings, the matcher and
its weights path, and the room box. A changed image or setting is a different key, never a stale
hit. Entries are written to a temporary name and renamed, so a killed run leaves no partial one.

A sealed session's timestamp (``Timestamp.sealing``) is kept sealed for the session's
recipients, as ``<key>.npz.sealed`` (``protocol.sealing.derived``, role ``depth``, name
``<key>``): the depth maps show the room as the cameras saw it. It is sealed in memory and read
back with the identity the timestamp was loaded with; a plaintext ``<key>.npz`` is never
written or read for it.

Each entry also names the libraries that made it (``made_by``: OpenCV, whose matcher and
filter make the depth, and open3d, which fuses it): they are not part of the key, because a
machine without them must read what one with them made, but a depth stage made by another
OpenCV is another depth (an evaluation says which made its jobs' depth, and warns when they
differ). An entry written before these were kept reads back with ``made_by`` empty (unknown).

On a hit, each ``DepthMap``'s rectified image is made again from the recorded left image (a
remap, milliseconds), and its ``disparity_px`` holds the disparity of the kept pixels only
(``fb / depth``; NaN elsewhere): what the matcher returned for rejected pixels is not stored,
and nothing after the depth stage reads it.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.metadata
import io
import json
import logging
import os
import zipfile
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, cast

import numpy as np
import xxhash

from protocol.camera import Intrinsics
from reconstructor.data.frames import Timestamp, right_from_left
from reconstructor.depth.stereo import DepthMap, rectifier
from reconstructor.errors import DepthCacheError

if TYPE_CHECKING:
    from protocol.sealing.derived import DerivedSeal
    from reconstructor.depth.fill import FillConfig
    from reconstructor.depth.fusion import FusedCloud, FusionConfig
    from reconstructor.depth.stereo_config import StereoConfig

log = logging.getLogger(__name__)


class DepthSettings(Protocol):
    """What the depth stage reads of a reconstruction's settings (``ReconstructConfig`` is one,
    resolved): the stage names only these, so it depends on no later stage's config."""

    @property
    def stereo(self) -> StereoConfig | None: ...
    @property
    def stereo_matcher(self) -> str: ...
    @property
    def stereo_weights(self) -> str: ...
    @property
    def fill(self) -> FillConfig: ...
    @property
    def fusion(self) -> FusionConfig: ...
    @property
    def room_bounds_m(self) -> tuple[float, ...]: ...


SEALED_SUFFIX = ".npz.sealed"
FORMAT_VERSION = 1  # bump when what the stage computes, or the stored layout, changes


def depth_libraries() -> dict[str, str]:
    """The versions of the libraries that compute the depth stage here: OpenCV (the matcher,
    the WLS filter, rectification) and open3d (fusion); "absent" where one is not installed."""
    return dict(_depth_libraries())


@functools.cache  # read once a process: every timestamp's stage names them
def _depth_libraries() -> dict[str, str]:
    out = {}
    for name, dist in (("opencv", None), ("open3d", "open3d")):
        try:
            if dist is None:
                import cv2

                out[name] = str(cv2.__version__)
            else:
                out[name] = importlib.metadata.version(dist)
        except (ImportError, importlib.metadata.PackageNotFoundError):
            out[name] = "absent"
    return out


def describe_made_by(made_by: dict[str, str]) -> str:
    """``made_by`` in words, e.g. "OpenCV 4.11.0, open3d 0.19.0"."""
    if not made_by:
        return "unknown libraries (made before the depth cache kept their versions)"
    names = {"opencv": "OpenCV", "open3d": "open3d"}
    order = [k for k in names if k in made_by] + sorted(k for k in made_by if k not in names)
    return ", ".join(f"{names.get(k, k)} {made_by[k]}" for k in order)


@dataclass
class DepthStage:
    """One timestamp's depth stage: ``depths`` per camera ("SN<serial>"), the ``fused`` cloud,
    ``clouds`` (the per-camera world points fusion merged; None on a hit from disk, where
    only the fused result is kept) and ``made_by``, the libraries that computed it (this
    machine's, unless it was read from disk)."""

    depths: dict[str, DepthMap]
    fused: FusedCloud
    clouds: list[tuple[np.ndarray, np.ndarray]] | None = None
    made_by: dict[str, str] = dataclasses.field(default_factory=depth_libraries)


def stage_key(ts: Timestamp, cfg: DepthSettings) -> str:
    """The digest of everything the depth stage of ``ts`` under ``cfg`` (resolved) reads."""
    h = xxhash.xxh3_128()
    settings = {
        "version": FORMAT_VERSION,
        "stereo": dataclasses.asdict(cfg.stereo) if cfg.stereo is not None else None,
        "fill": dataclasses.asdict(cfg.fill),
        "fusion": dataclasses.asdict(cfg.fusion),
        "matcher": cfg.stereo_matcher,
        "weights": cfg.stereo_weights,
        "room_bounds_m": list(cfg.room_bounds_m),
    }
    h.update(json.dumps(settings, sort_keys=True, default=str).encode())
    for left, right in ts.stereo_pairs():
        for frame in (left, right):
            cam = frame.camera
            h.update(f"{frame.camera_serial}:{frame.side}:{frame.image_rgb.shape}".encode())
            h.update(json.dumps(dataclasses.asdict(cam.intrinsics)).encode())
            h.update(np.ascontiguousarray(cam.pose.matrix, dtype=np.float64).tobytes())
            h.update(np.ascontiguousarray(frame.image_rgb).data)
    return h.hexdigest()


class DepthCache:
    """Depth stages by key: the last ``memory`` in memory and, with ``folder``, all on disk."""

    def __init__(self, folder: Path | None = None, memory: int = 1) -> None:
        self.folder = Path(folder) if folder is not None else None
        self.memory = memory
        self._recent: OrderedDict[str, DepthStage] = OrderedDict()
        self.hits = self.misses = 0
        self.served: list[dict[str, str]] = []  # made_by of each stage given or stored, in order
        if self.folder is not None:
            if self.folder.exists() and not self.folder.is_dir():
                raise DepthCacheError(f"depth cache {self.folder} is a file; give a folder")
            try:
                self.folder.mkdir(parents=True, exist_ok=True)
            except OSError as e:
                raise DepthCacheError(
                    f"cannot make the depth cache folder {self.folder}: {e.strerror}"
                ) from None
            if not os.access(self.folder, os.W_OK):
                raise DepthCacheError(f"depth cache folder {self.folder} is not writable")

    def get(self, ts: Timestamp, cfg: DepthSettings) -> DepthStage | None:
        key = stage_key(ts, cfg)
        stage = self._recent.get(key)
        if stage is None and self.folder is not None:
            path = self.folder / _file_name(key, ts.sealing)
            if path.is_file():
                try:
                    stage = _read(path, ts, cfg, key)
                except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
                    log.warning("depth cache entry %s unreadable (%s); computing it again", path, e)
        if stage is None:
            self.misses += 1
            return None
        self.hits += 1
        self.served.append(stage.made_by)
        self._remember(key, stage)
        return stage

    def put(self, ts: Timestamp, cfg: DepthSettings, stage: DepthStage) -> None:
        key = stage_key(ts, cfg)
        self.served.append(stage.made_by)
        self._remember(key, stage)
        if self.folder is not None:
            _write(self.folder / _file_name(key, ts.sealing), stage, key, ts.sealing)

    def _remember(self, key: str, stage: DepthStage) -> None:
        if self.memory <= 0:
            return
        self._recent[key] = stage
        self._recent.move_to_end(key)
        while len(self._recent) > self.memory:
            self._recent.popitem(last=False)


def _file_name(key: str, seal: DerivedSeal | None) -> str:
    """A plaintext session's entry is ``<key>.npz``; a sealed one's, ``<key>.npz.sealed``:
    the same ``.npz`` sealed for the session's recipients (``protocol.sealing.derived``), so a
    folder shared by both never serves one as the other."""
    return f"{key}.npz" if seal is None else f"{key}{SEALED_SUFFIX}"


def _write(path: Path, stage: DepthStage, key: str, seal: DerivedSeal | None) -> None:
    arrays: dict[str, np.ndarray] = {
        "fused_points_m": stage.fused.points_m,
        "fused_colours": stage.fused.colours,
    }
    meta: dict = {"fused_stats": stage.fused.stats, "depths": {}, "made_by": stage.made_by}
    for name, d in stage.depths.items():
        arrays[f"{name}/depth_m"] = d.depth_m
        arrays[f"{name}/valid"] = np.packbits(d.valid)
        arrays[f"{name}/rect_from_left"] = d.rect_from_left
        meta["depths"][name] = {
            "intrinsics": dataclasses.asdict(d.intrinsics),
            "baseline_m": d.baseline_m,
            "shape": list(d.depth_m.shape),
        }
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        # numpy's stubs (2.1 on) let a ** key fill savez's allow_pickle flag; no key here is
        # that name, and numpy 1.26 (supported) has no flag to pass instead: the arrays as Any
        if seal is None:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, **cast(dict[str, Any], arrays))
        else:  # sealed in memory: the plaintext never reaches the disk
            buf = io.BytesIO()
            np.savez_compressed(buf, **cast(dict[str, Any], arrays))
            tmp.write_bytes(seal.seal("depth", key, buf.getbuffer()))
        os.replace(tmp, path)
    except OSError as e:  # a full disk loses the cache entry, never the reconstruction
        log.warning("could not write depth cache entry %s: %s", path, e)
        tmp.unlink(missing_ok=True)


def _read(path: Path, ts: Timestamp, cfg: DepthSettings, key: str) -> DepthStage:
    from reconstructor.depth.fusion import FusedCloud

    assert cfg.stereo is not None, "resolve the config first"
    source: Path | io.BytesIO = path
    if ts.sealing is not None:
        source = io.BytesIO(ts.sealing.open("depth", key, path.read_bytes(), str(path)))
    with np.load(source, allow_pickle=False) as z:
        meta = json.loads(z["meta"].tobytes().decode())
        fused = FusedCloud(z["fused_points_m"], z["fused_colours"], meta["fused_stats"])
        depths: dict[str, DepthMap] = {}
        for left, right in ts.stereo_pairs():
            name = f"SN{left.camera_serial}"
            m = meta["depths"][name]
            shape = tuple(m["shape"])
            depth = z[f"{name}/depth_m"]
            valid = np.unpackbits(z[f"{name}/valid"], count=shape[0] * shape[1]).astype(bool)
            intr = Intrinsics(**m["intrinsics"])
            rect = rectifier(
                left.camera.intrinsics,
                right.camera.intrinsics,
                right_from_left(left.camera, right.camera),
                cfg.stereo.scale_for(left.camera.intrinsics.width_px),
                cfg.stereo.rectify_alpha,
            )
            rgb = rect.rectify(left.image_rgb, right.image_rgb)[0]
            if rgb.shape[:2] != shape:
                raise ValueError(f"{name}: rectified image {rgb.shape[:2]} is not {shape}")
            valid = valid.reshape(shape)
            disparity = np.full(shape, np.nan, np.float32)
            disparity[valid] = (intr.fx_px * m["baseline_m"]) / depth[valid]
            depths[name] = DepthMap(
                depth_m=depth,
                valid=valid,
                disparity_px=disparity,
                intrinsics=intr,
                rect_from_left=z[f"{name}/rect_from_left"],
                baseline_m=float(m["baseline_m"]),
                rgb=rgb,
            )
    made_by = meta.get("made_by", {})
    if not isinstance(made_by, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in made_by.items()
    ):
        raise ValueError(f"made_by {made_by!r} is not {{library: version}}")
    return DepthStage(depths=depths, fused=fused, made_by=made_by)
